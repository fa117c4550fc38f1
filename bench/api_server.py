"""One API process for the read benches (uvicorn on ``service.app``, the filesystem
broker, rate limits and queue caps out of the way): start it, wait for /healthz, stop it,
and its CPU seconds (``bench/load.py``, ``bench/reads.py``, ``bench/dataset_upload.py``)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent

HOST = "127.0.0.1"  # loopback only
API = "/api/v1"
RATE_LIMIT = 10_000_000
QUEUED_CAP = 10_000_000


def free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return s.getsockname()[1]


def start_server(tmp: Path, db_url: str, port: int, workers: int = 1) -> subprocess.Popen:
    env = {
        **os.environ,
        "SVROBS_DATABASE_URL": db_url,
        "SVROBS_BROKER_URL": "filesystem://",
        "SVROBS_BROKER_DIR": str(tmp / "broker"),
        "SVROBS_VAR_DIR": str(tmp),
        "SVROBS_RATE_LIMIT_PER_MINUTE": str(RATE_LIMIT),
        "SVROBS_MAX_QUEUED_JOBS_PER_TEAM": str(QUEUED_CAP),
        "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
    }
    cmd = [
        sys.executable,
        "-m",
        "uvicorn",
        "service.app:app",
        "--host",
        HOST,
        "--port",
        str(port),
        "--workers",
        str(workers),
        "--no-access-log",
        "--log-level",
        "warning",
        "--http",  # as svrobs serve runs it (service.http.request_deadlines)
        "service.http.request_deadlines:RequestDeadlineProtocol",
    ]
    with open(tmp / "api.log", "wb") as log:  # the child keeps its own descriptor
        return subprocess.Popen(
            cmd,
            env=env,
            cwd=str(ROOT),
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )


def stop_server(proc: subprocess.Popen) -> None:
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5)


def wait_ready(base: str, proc: subprocess.Popen, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the API exited with code {proc.returncode}")
        try:
            if httpx.get(f"{base}/healthz", timeout=1.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise RuntimeError("the API did not answer /healthz in time")


def cpu_seconds(root_pid: int) -> float | None:
    """User + system CPU of a process and its children (Linux /proc), else None."""
    try:
        tick = os.sysconf("SC_CLK_TCK")
        total = 0.0
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            try:
                fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            pid, ppid = int(entry), int(fields[1])
            if pid == root_pid or ppid == root_pid:
                total += (int(fields[11]) + int(fields[12])) / tick
        return total
    except (OSError, ValueError, AttributeError):
        return None
