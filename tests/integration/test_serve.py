"""`svrobs serve` (svrobs_cli.serve) as a user runs it: one command, Ctrl-C stops all;
a worker killed with SIGKILL is restarted (``/readyz`` 503 until it is back, the API
answering throughout); ``--host`` / ``--port``; a port in use is one line."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
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


def _serve_env(tmp_path, **extra) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("SVROBS_")}
    env.update(
        SVROBS_DATABASE_URL=f"sqlite:///{tmp_path / 'var' / 'svrobs.db'}",
        SVROBS_BROKER_DIR=str(tmp_path / "var" / "broker"),
        SVROBS_VAR_DIR=str(tmp_path / "var"),
        PYTHONUNBUFFERED="1",
        **extra,
    )
    return env


def _start_serve(tmp_path, port, *args: str):
    """``svrobs serve`` with its API on ``port`` (SVROBS_API_PORT, or ``--port`` in args)."""
    env = _serve_env(tmp_path, **({} if "--port" in args else {"SVROBS_API_PORT": str(port)}))
    log = open(tmp_path / "serve.log", "wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "svrobs_cli", "serve", *args],
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
                if "svrobs is running" in text:  # the box, printed once it is up
                    return text
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    raise AssertionError(log.read_text())


def _child_pids(text: str) -> dict[str, int]:
    return {m[0]: int(m[1]) for m in re.findall(r"started (\w+) \(pid (\d+)\)", text)}


def _readyz(port: int) -> int:
    try:
        return httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=5).status_code
    except httpx.HTTPError:
        return 0


def _stop(proc, sig=signal.SIGINT) -> None:
    if proc.poll() is None:
        os.kill(proc.pid, sig)
        try:
            proc.wait(40)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


@contextlib.contextmanager
def _serving(tmp_path, port, *args: str):
    """``svrobs serve`` up (its box printed): ``(proc, log, text so far)``; stopped after."""
    proc, log = _start_serve(tmp_path, port, *args)
    try:
        yield proc, log, _wait_ready(proc, log, port)
    finally:
        _stop(proc)


def test_serve_from_first_start_to_ctrl_c_and_the_next_start(tmp_path):
    """One state folder through its life (each start of ``svrobs serve`` costs seconds):
    the first start prints the key box on ``--host`` / ``--port`` and the API takes
    that key; ``make run`` again while it runs (the same port, or another one as the
    port message suggests) is one line naming the running one, and the stack keeps its
    worker's pid file and stays ready; Ctrl-C stops every child; the next start on the
    freed folder prints no new key."""
    port, other = free_port(), free_port()
    with _serving(tmp_path, port, "--host", "127.0.0.1", "--port", str(port)) as (proc, log, text):
        key = re.search(r"(svr_[a-z0-9]{8}_\S+)", text).group(1)
        assert f"svrobs is running: open http://127.0.0.1:{port}/" in text
        assert f"export SVROBS_URL=http://127.0.0.1:{port} SVROBS_API_KEY={key}" in text
        r = httpx.get(
            f"http://127.0.0.1:{port}/api/v1/jobs", headers={"Authorization": f"Bearer {key}"}
        )
        assert r.status_code == 200, r.text
        pids = _child_pids(text)
        assert set(pids) == {"api", "worker1", "beat"}
        pid_files = sorted((tmp_path / "var" / "run").glob("*.pid"))
        assert pid_files, log.read_text()
        for p in (port, other):
            second = subprocess.Popen(
                [sys.executable, "-m", "svrobs_cli", "serve", "--port", str(p)],
                cwd=str(ROOT),
                env=_serve_env(tmp_path),
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                start_new_session=True,
            )
            try:
                out, err = second.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                _stop(second)
                raise AssertionError(f"a second serve on port {p} started") from None
            assert second.returncode == 2, out + err
            assert err.strip() == (
                f"error: svrobs serve already runs on the state folder {tmp_path / 'var'} "
                f"(pid {proc.pid}, http://127.0.0.1:{port}); use that one, or stop it "
                "(Ctrl-C in its terminal) before starting another"
            )
            assert out == ""
        assert sorted((tmp_path / "var" / "run").glob("*.pid")) == pid_files
        assert _readyz(port) == 200
        os.kill(proc.pid, signal.SIGINT)  # what Ctrl-C sends
        assert proc.wait(40) == 0, log.read_text()
        time.sleep(0.5)
        assert not [n for n, p in pids.items() if _alive(p)], log.read_text()
    # stopped: the folder is free for the next start, which prints no new key
    with _serving(tmp_path, other) as (_proc, _log, text):
        assert f"http://127.0.0.1:{other}/" in text
        assert "svr_" not in text.replace("svr_...", "")
        assert "admin API key: printed on first start" in text


@pytest.mark.faults  # kills a worker: `make test-faults`
def test_a_killed_worker_is_restarted_and_readyz_says_so(tmp_path):
    port = free_port()
    with _serving(tmp_path, port) as (proc, log, text):
        key = re.search(r"(svr_[a-z0-9]{8}_\S+)", text).group(1)
        pids = _child_pids(text)
        pool = [int(p) for p in os.popen(f"pgrep -P {pids['worker1']}").read().split()]
        assert pool  # the prefork pool

        os.kill(pids["worker1"], signal.SIGKILL)
        seen, api_codes = [], []
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and not (503 in seen and seen[-1] == 200):
            seen.append(_readyz(port))
            api_codes.append(httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=5).status_code)
            time.sleep(0.1)
        assert 503 in seen and seen[-1] == 200, (seen, log.read_text()[-3000:])
        assert seen[: seen.index(503)] == [200] * seen.index(503)  # 200 only until it saw the death
        assert set(api_codes) == {200}  # the API answered throughout
        out = log.read_text()
        assert re.search(r"worker1 \(pid \d+\) exited \(killed by SIGKILL\).*restarting in", out)
        restarted = re.search(r"restarted worker1 \(pid (\d+); restart 1\)", out)
        assert restarted, out[-3000:]
        assert proc.poll() is None
        assert not [p for p in pool if _alive(p)]  # the old pool went with its worker

        # a job through the restarted worker
        headers = {"Authorization": f"Bearer {key}"}
        spec = {"systems": ["paper-stable"], "sigma_w": [0.1], "N": [10, 20], "reps": 2}
        r = httpx.post(f"http://127.0.0.1:{port}/api/v1/jobs", json=spec, headers=headers)
        assert r.status_code == 202, r.text
        job = r.json()
        deadline = time.monotonic() + 120
        while job["status"] not in ("succeeded", "failed", "cancelled"):
            assert time.monotonic() < deadline, job
            time.sleep(0.3)
            job = httpx.get(
                f"http://127.0.0.1:{port}/api/v1/jobs/{job['id']}", headers=headers
            ).json()
        assert job["status"] == "succeeded", job

        new_worker = int(restarted.group(1))
        os.kill(proc.pid, signal.SIGTERM)
        assert proc.wait(40) == 0, log.read_text()[-3000:]
        time.sleep(0.5)
        assert not [p for p in [*pids.values(), new_worker] if _alive(p)], log.read_text()


def test_a_port_in_use_is_one_line_and_starts_nothing(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        run = subprocess.run(
            [sys.executable, "-m", "svrobs_cli", "serve", "--port", str(port)],
            cwd=str(ROOT),
            env=_serve_env(tmp_path),
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert run.returncode == 2
    assert run.stderr.strip() == (
        f"error: port {port} is in use; pick another with --port (make run PORT=...)"
    )
    assert run.stdout == ""  # nothing migrated, nothing started
    assert not (tmp_path / "var").exists()
