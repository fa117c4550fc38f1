"""The README's five-minute tour, run as written: `svrobs serve` on an embedded stack
(what `make run` starts) that already holds other jobs, then the tour's shell block,
line for line, in bash with `set -euo pipefail`. The block's first line
(`export SVROBS_URL=... SVROBS_API_KEY=svr_...`) is the one placeholder: the test
exports the URL of its server and the key it printed.

The other jobs take the lowest ids and differ from the tour's in their grid, so a
command that acted on a fixed id instead of the one the tour's submit printed would
write another job's rows, summary, comparison, report or schedule, and fail here."""

from __future__ import annotations

import csv
import io
import json
import os
import re
import signal
import subprocess
import time

import httpx
import pytest

from .conftest import ROOT, free_port
from .test_serve import _start_serve, _wait_ready

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

PLACEHOLDER = re.compile(r"^export SVROBS_URL=\S+ SVROBS_API_KEY=svr_\.\.\.")
# jobs the server holds before the tour: grids unlike the tour's (other cell counts)
OTHER_JOBS = [
    {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10, 20], "reps": 2, "seed": 7},
    {"systems": ["paper-unstable"], "sigma_w": [0.1], "N": [30], "reps": 3, "seed": 8},
    {"systems": ["paper-stable"], "sigma_w": [0.1, 1.0], "N": [50], "reps": 1, "seed": 1},
]


def tour_block() -> list[str]:
    """The first ```sh block under the README's tour heading, as lines."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## A five-minute tour", 1)[1]
    block = section.split("```sh\n", 1)[1].split("\n```", 1)[0]
    return block.splitlines()


def test_tour_block_starts_with_the_one_placeholder():
    lines = tour_block()
    assert PLACEHOLDER.match(lines[0]), lines[0]
    assert not any("svr_..." in line for line in lines[1:])


def _wait_all_finished(api: httpx.Client, ids: list[int], timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        states = {i: api.get(f"/jobs/{i}").json()["status"] for i in ids}
        if all(st in ("succeeded", "failed", "cancelled") for st in states.values()):
            assert set(states.values()) == {"succeeded"}, states
            return
        time.sleep(0.5)
    raise AssertionError(f"other jobs not finished: {states}")


def test_readme_tour_runs_as_written(tmp_path):
    lines = tour_block()[1:]  # all but the placeholder export
    port = free_port()
    proc, log = _start_serve(tmp_path, port)
    try:
        text = _wait_ready(proc, log, port)
        key = re.search(r"(svr_[a-z0-9]{8}_\S+)", text).group(1)
        url = f"http://127.0.0.1:{port}"
        headers = {"Authorization": f"Bearer {key}"}
        api = httpx.Client(base_url=f"{url}/api/v1", headers=headers, timeout=30)
        others = [
            api.post("/jobs", json={**spec, "name": f"other-{i}"}).json()["id"]
            for i, spec in enumerate(OTHER_JOBS)
        ]
        _wait_all_finished(api, others)

        work = tmp_path / "tour"
        work.mkdir()
        (work / ".venv").symlink_to(ROOT / ".venv")  # the tour runs from a checkout
        env = {k: v for k, v in os.environ.items() if not k.startswith("SVROBS_")}
        env.update(SVROBS_URL=url, SVROBS_API_KEY=key, HOME=str(tmp_path))
        script = "set -euo pipefail\n" + "\n".join(lines) + "\n"
        run = subprocess.run(
            ["bash", "-c", script], cwd=work, env=env, capture_output=True, text=True, timeout=240
        )
        assert run.returncode == 0, f"stdout:\n{run.stdout}\nstderr:\n{run.stderr}"
        assert key not in run.stdout + run.stderr + log.read_text().replace(text, "")

        # the tour made two jobs, after the others, and every command acted on them
        jobs = {j["name"]: j for j in api.get("/jobs", params={"limit": 100}).json()["items"]}
        assert all(j["status"] == "succeeded" for j in jobs.values()), jobs
        tour, tour2 = jobs["tour"], jobs["tour-seed8"]
        assert min(tour["id"], tour2["id"]) > max(others)
        other_cells = {jobs[f"other-{i}"]["n_cells"] for i in range(len(OTHER_JOBS))}
        assert tour["n_cells"] not in other_cells  # so a wrong job cannot pass for it

        # results: the tour job's rows, byte for byte as the API exports them
        csv_bytes = (work / "tour.csv").read_bytes()
        assert len(csv_bytes.splitlines()) == tour["n_cells"] + 1
        want = api.get(f"/jobs/{tour['id']}/results", params={"format": "csv"}).content
        assert csv_bytes == want

        # summary: one line per group of the tour job's summary
        groups = api.get(f"/jobs/{tour['id']}/summary").json()["groups"]
        rows = list(csv.DictReader(io.StringIO((work / "summary.tsv").read_text()), delimiter="\t"))
        assert len(rows) == len(groups)
        key_of = lambda g: (  # the TSV's blank gamma is OLS's null
            g["system"],
            float(g["sigma_w"]),
            int(g["N"]),
            g["estimator"],
            float(g["gamma"]) if g["gamma"] not in (None, "") else None,
        )
        assert {key_of(r) for r in rows} == {key_of(g) for g in groups}

        # the curl line printed the tour job's filtered page
        page = api.get(
            f"/jobs/{tour['id']}/results?system=paper-stable&N=50&estimator=svr&gamma=0.05&limit=5"
        ).json()
        assert page["items"] and json.dumps(page) in _json_lines(run.stdout)

        # compare: exactly the two tour jobs (the table's first column)
        compared = {
            int(f[0])
            for f in (ln.split("\t") for ln in run.stdout.splitlines())
            if len(f) == 6 and f[0].isdigit() and f[2] in ("ols", "svr")
        }
        assert compared == {tour["id"], tour2["id"]}

        # report and schedule: made from the tour job
        html = (work / "report" / "report.html").read_text()
        assert re.search(r"Job tour(?![\w-])", html) and "Job other-" not in html
        (nightly,) = [s for s in api.get("/schedules").json() if s["name"] == "nightly"]
        assert nightly["spec_template"] == api.get(f"/jobs/{tour['id']}").json()["spec"]
        api.close()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(40)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()


def _json_lines(stdout: str) -> set[str]:
    """Every JSON document that starts a stdout line, re-serialised (curl prints no
    newline after it, so the next command's output may follow on the same line)."""
    out = set()
    for line in stdout.splitlines():
        if line.startswith("{"):
            try:
                out.add(json.dumps(json.JSONDecoder().raw_decode(line)[0]))
            except ValueError:
                pass
    return out
