"""The README's five-minute tour, run as written: `svrobs serve` on a fresh embedded
stack (what `make run` starts), then the tour's shell block, line for line, in bash
with `set -euo pipefail`. The block's first line (`export SVROBS_URL=... SVROBS_API_KEY=svr_...`)
is the one placeholder: the test exports the URL of its server and the key it printed."""

from __future__ import annotations

import os
import re
import signal
import subprocess

import httpx
import pytest

from .conftest import ROOT, free_port
from .test_serve import _start_serve, _wait_ready

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

PLACEHOLDER = re.compile(r"^export SVROBS_URL=\S+ SVROBS_API_KEY=svr_\.\.\.")


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


def test_readme_tour_runs_as_written(tmp_path):
    lines = tour_block()[1:]  # all but the placeholder export
    port = free_port()
    proc, log = _start_serve(tmp_path, port)
    try:
        text = _wait_ready(proc, log, port)
        key = re.search(r"(svr_[a-z0-9]{8}_\S+)", text).group(1)
        work = tmp_path / "tour"
        work.mkdir()
        (work / ".venv").symlink_to(ROOT / ".venv")  # the tour runs from a checkout
        env = {k: v for k, v in os.environ.items() if not k.startswith("SVROBS_")}
        env.update(SVROBS_URL=f"http://127.0.0.1:{port}", SVROBS_API_KEY=key, HOME=str(tmp_path))
        script = "set -euo pipefail\n" + "\n".join(lines) + "\n"
        run = subprocess.run(
            ["bash", "-c", script], cwd=work, env=env, capture_output=True, text=True, timeout=240
        )
        assert run.returncode == 0, f"stdout:\n{run.stdout}\nstderr:\n{run.stderr}"
        assert key not in run.stdout + run.stderr + log.read_text().replace(text, "")

        # what the tour says it made is there and agrees with the API
        headers = {"Authorization": f"Bearer {key}"}
        jobs = httpx.get(f"{env['SVROBS_URL']}/api/v1/jobs", headers=headers).json()
        assert jobs and all(j["status"] == "succeeded" for j in jobs["items"]), jobs
        first = min(j["id"] for j in jobs["items"])
        n_cells = next(j["n_cells"] for j in jobs["items"] if j["id"] == first)
        csv_lines = (work / "tour.csv").read_text().splitlines()
        assert len(csv_lines) == n_cells + 1
        assert (work / "report" / "report.html").stat().st_size > 10_000
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(40)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
