"""The README's five-minute tour, run as written: `svrobs serve` on an embedded stack
(what `make run` starts) that already holds other jobs and another dataset, then the
tour's two shell blocks (the first under the tour's heading, then the one of its
measured-data part), line for line, in one bash with `set -euo pipefail`, from a
folder that has the checkout's `.venv` and `docs`. The first block's first line
(`export SVROBS_URL=... SVROBS_API_KEY=svr_...`) is the one placeholder: the test
exports the URL of its server and the key it printed.

The other jobs and the other dataset take the lowest ids and differ from the tour's
in their grid and shape, so a command that acted on a fixed id instead of the one the
tour's upload or submit printed would write another job's rows, summary, comparison,
report, schedule, validation or model, and fail here."""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import re
import signal
import subprocess
import time

import httpx
import numpy as np
import pytest
import scipy.io

from .conftest import ROOT, free_port
from .test_serve import _start_serve, _wait_ready

pytestmark = [pytest.mark.integration, pytest.mark.timeout(420)]

PLACEHOLDER = re.compile(r"^export SVROBS_URL=\S+ SVROBS_API_KEY=svr_\.\.\.")
# jobs the server holds before the tour: grids unlike the tour's (other cell counts)
OTHER_JOBS = [
    {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10, 20], "reps": 2, "seed": 7},
    {"systems": ["paper-unstable"], "sigma_w": [0.1], "N": [30], "reps": 3, "seed": 8},
    {"systems": ["paper-stable"], "sigma_w": [0.1, 1.0], "N": [50], "reps": 1, "seed": 1},
]


TOUR = "## A five-minute tour"
MEASURED = "### The tour on measured data"
PLANT = ROOT / "docs" / "examples" / "plant.csv"
OTHER_DATASET = ROOT / "docs" / "examples" / "rollouts.csv"  # 3 rollouts: not the plant's 24


def sh_block(heading: str) -> list[str]:
    """The first ```sh block after the README's line ``heading`` and before the next
    heading, as lines."""
    lines = (ROOT / "README.md").read_text().splitlines()
    assert lines.count(heading) == 1, f"README.md has no single line {heading!r}"
    out: list[str] | None = None
    for line in lines[lines.index(heading) + 1 :]:
        if out is None:
            assert not line.startswith("#"), f"no sh block under {heading!r}"
            if line == "```sh":
                out = []
        elif line == "```":
            return out
        else:
            out.append(line)
    raise AssertionError(f"the sh block under {heading!r} does not end")


def tour_block() -> list[str]:
    """The tour's first block, then its measured-data block."""
    return sh_block(TOUR) + sh_block(MEASURED)


def test_tour_block_starts_with_the_one_placeholder():
    lines = tour_block()
    assert PLACEHOLDER.match(lines[0]), lines[0]
    assert not any("svr_..." in line for line in lines[1:])
    measured = sh_block(MEASURED)
    assert any("datasets upload docs/examples/plant.csv" in ln for ln in measured)
    assert any(ln.startswith(".venv/bin/svrobs model ") for ln in measured)


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
        r = api.post(
            "/datasets",
            files={"file": ("other.csv", OTHER_DATASET.read_bytes())},
            data={"name": "other-ds"},
        )
        assert r.status_code == 201, r.text
        other_ds = r.json()["id"]
        spec = {"dataset": other_ds, "N": [2], "holdout": 1, "reps": 1, "name": "other-ds-job"}
        others.append(api.post("/jobs", json=spec).json()["id"])
        _wait_all_finished(api, others)

        work = tmp_path / "tour"
        work.mkdir()
        for part in (".venv", "docs"):  # the tour runs from a checkout
            (work / part).symlink_to(ROOT / part)
        env = {k: v for k, v in os.environ.items() if not k.startswith("SVROBS_")}
        env.update(SVROBS_URL=url, SVROBS_API_KEY=key, HOME=str(tmp_path))
        script = "set -euo pipefail\n" + "\n".join(lines) + "\n"
        run = subprocess.run(
            ["bash", "-c", script], cwd=work, env=env, capture_output=True, text=True, timeout=330
        )
        assert run.returncode == 0, f"stdout:\n{run.stdout}\nstderr:\n{run.stderr}"
        assert key not in run.stdout + run.stderr + log.read_text().replace(text, "")

        # the tour made two jobs, after the others, and every command acted on them
        jobs = {j["name"]: j for j in api.get("/jobs", params={"limit": 100}).json()["items"]}
        assert all(j["status"] == "succeeded" for j in jobs.values()), jobs
        tour, tour2 = jobs["tour"], jobs["tour-seed8"]
        assert min(tour["id"], tour2["id"]) > max(others)
        other_cells = {jobs[f"other-{i}"]["n_cells"] for i in range(len(OTHER_JOBS))}
        other_cells.add(jobs["other-ds-job"]["n_cells"])
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
            if len(f) == 7 and f[0].isdigit() and f[2] in ("ols", "svr")  # job, N, estimator, gamma
        }
        assert compared == {tour["id"], tour2["id"]}

        # report and schedule: made from the tour job
        html = (work / "report" / "report.html").read_text()
        assert re.search(r"Job tour(?![\w-])", html) and "Job other-" not in html
        (nightly,) = [s for s in api.get("/schedules").json() if s["name"] == "nightly"]
        assert nightly["spec_template"] == api.get(f"/jobs/{tour['id']}").json()["spec"]

        # measured data: the plant's file uploaded once, a job on it, its validation, a model
        (plant,) = [d for d in api.get("/datasets").json()["items"] if d["name"] == "plant"]
        assert plant["id"] > other_ds and plant["rollouts"] == 24
        assert plant["sha256"] == hashlib.sha256(PLANT.read_bytes()).hexdigest()
        fit = jobs["plant-fit"]
        assert fit["id"] > max(others) and fit["n_cells"] not in other_cells
        assert api.get(f"/jobs/{fit['id']}").json()["spec"]["dataset"] == plant["id"]
        validation = api.get(f"/jobs/{fit['id']}/validation").json()
        assert validation["dataset"] == plant["id"] and validation["holdout"] == 4
        for m in validation["models"]:  # the validation command printed the API's fits
            gamma = "" if m["gamma"] is None else f" gamma={m['gamma']:g}"
            x1 = m["validation"]["one_step_fit"][0]
            assert f"{m['estimator']}{gamma}: one-step fit x1 {x1:.1f} %" in run.stdout
        (rec,) = [
            r
            for r in api.get(f"/jobs/{fit['id']}/results", params={"limit": 1000}).json()["items"]
            if (r["N"], r["estimator"], r["rep"]) == (20, "svr", 0)
        ]
        mat = scipy.io.loadmat(work / "plant_svr.mat")
        assert np.array_equal(mat["A_hat"], np.array(rec["A_hat"]))
        assert np.array_equal(mat["B_hat"], np.array(rec["B_hat"]))
        assert json.loads(str(mat["provenance"][0]))["job_id"] == fit["id"]
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
