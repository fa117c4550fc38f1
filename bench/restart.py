"""How fast `svrobs serve` brings a killed worker back: SIGKILL the worker of an embedded
stack a few times and time /readyz.

    .venv/bin/python bench/restart.py              # 5 kills, 3 s apart, port 8152
    .venv/bin/python bench/restart.py --kills 3 --port 8153

For each kill it prints the seconds from the kill until /readyz answers 503, until it
answers 200 again (the restarted worker's pid file is there and its process alive),
and until the new worker logs "ready." (it consumes); then the backoff delays the
supervisor logged. Each kill comes within a minute of the restart before it, so the
delays double (docs/performance.md#restarts-and-stops).
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kills", type=int, default=5)
    p.add_argument("--gap", type=float, default=3.0, help="seconds between a restart and a kill")
    p.add_argument("--port", type=int, default=8152)
    args = p.parse_args()
    var = Path(tempfile.mkdtemp(prefix="svrobs-restart-"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("SVROBS_")}
    env.update(
        SVROBS_VAR_DIR=str(var),
        SVROBS_DATABASE_URL=f"sqlite:///{var / 'svrobs.db'}",
        SVROBS_BROKER_DIR=str(var / "broker"),
    )
    log_path = var / "serve.log"
    with open(log_path, "wb") as log:
        serve = subprocess.Popen(
            [sys.executable, "-m", "svrobs_cli", "serve", "--port", str(args.port)],
            cwd=ROOT,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    url = f"http://127.0.0.1:{args.port}/readyz"

    def readyz() -> int:
        try:
            return httpx.get(url, timeout=5).status_code
        except httpx.HTTPError:
            return 0

    def text() -> str:
        return log_path.read_text(errors="replace")

    try:
        while "svrobs is running" not in text():
            if serve.poll() is not None:
                sys.exit(text()[-3000:])
            time.sleep(0.2)
        print("kill  ->503 s  ->200 s  ->consuming s")
        for i in range(args.kills):
            time.sleep(args.gap)
            pid = int((var / "run" / "worker1.pid").read_text())
            t0 = time.monotonic()
            os.kill(pid, signal.SIGKILL)
            while readyz() != 503:
                time.sleep(0.02)
            down = time.monotonic() - t0
            while readyz() != 200:
                time.sleep(0.05)
            up = time.monotonic() - t0
            while text().count(" ready.") < i + 2:
                time.sleep(0.05)
            consuming = time.monotonic() - t0
            print(f"{i + 1:4d}  {down:7.2f}  {up:7.2f}  {consuming:12.2f}", flush=True)
        print("backoff delays (s):", ", ".join(re.findall(r"restarting in (\S+) s", text())))
    finally:
        serve.send_signal(signal.SIGINT)
        try:
            serve.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(serve.pid, signal.SIGKILL)
            serve.wait()


if __name__ == "__main__":
    main()
