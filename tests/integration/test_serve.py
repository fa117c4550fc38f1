"""`svrobs serve` (svrobs_cli.serve) as a user runs it: one command, Ctrl-C stops all."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import httpx
import pytest

from .conftest import ROOT, free_port

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie not yet reaped by init counts as gone
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def _start_serve(tmp_path, port):
    env = {k: v for k, v in os.environ.items() if not k.startswith("SVROBS_")}
    env.update(
        SVROBS_DATABASE_URL=f"sqlite:///{tmp_path / 'var' / 'svrobs.db'}",
        SVROBS_BROKER_DIR=str(tmp_path / "var" / "broker"),
        SVROBS_VAR_DIR=str(tmp_path / "var"),
        SVROBS_API_PORT=str(port),
        PYTHONUNBUFFERED="1",
    )
    log = open(tmp_path / "serve.log", "wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "svrobs_cli", "serve"],
        cwd=str(ROOT),
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    return proc, tmp_path / "serve.log"


def _wait_ready(proc, log, port, timeout=90):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, log.read_text()
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2).status_code == 200:
                text = log.read_text()
                if "worker1" in text and "beat" in text:
                    return text
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    raise AssertionError(log.read_text())


def _child_pids(text: str) -> dict[str, int]:
    return {m[0]: int(m[1]) for m in re.findall(r"started (\w+) \(pid (\d+)\)", text)}


def test_serve_first_start_prints_key_and_ctrl_c_stops_everything(tmp_path):
    port = free_port()
    proc, log = _start_serve(tmp_path, port)
    try:
        text = _wait_ready(proc, log, port)
        key = re.search(r"(svr_[a-z0-9]{8}_\S+)", text).group(1)
        r = httpx.get(
            f"http://127.0.0.1:{port}/api/v1/jobs", headers={"Authorization": f"Bearer {key}"}
        )
        assert r.status_code == 200, r.text
        pids = _child_pids(text)
        assert set(pids) == {"api", "worker1", "beat"}
        os.kill(proc.pid, signal.SIGINT)  # what Ctrl-C sends
        assert proc.wait(40) == 0, log.read_text()
        time.sleep(0.5)
        assert not [n for n, p in pids.items() if _alive(p)], log.read_text()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()

    # second start: same DB, no new key printed
    proc, log = _start_serve(tmp_path, port)
    try:
        text = _wait_ready(proc, log, port)
        assert "svr_" not in text
        pids = _child_pids(text)
        # a child dying takes the whole stack down, non-zero
        os.killpg(pids["worker1"], signal.SIGKILL)
        assert proc.wait(40) != 0
        assert "worker1 exited" in log.read_text()
        time.sleep(0.5)
        assert not [n for n, p in pids.items() if _alive(p)], log.read_text()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
