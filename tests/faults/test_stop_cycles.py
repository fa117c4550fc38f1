"""Stops leave nothing: 50 stop cycles of ``svrobs serve`` (the embedded stack, real
processes) at seeded random moments, each followed by a scan of /proc.

A cycle starts ``svrobs serve`` on a copy of one migrated SQLite database, with an
environment variable whose value is unique to the cycle (every process of the stack,
pool processes included, inherits it), brings the stack to one moment:

- ``startup``: 0.3-3 s after the command, whatever is running by then;
- ``idle``: the stack up, nothing to do;
- ``mid-job``: a unit running;
- ``report``: a report request being built by the API;
- ``pool-kills``: pool processes SIGKILLed one to three times while units run;
- ``restart``: the worker SIGKILLed, the supervisor about to restart it or restarting it;

and stops it one way: SIGINT to the supervisor's process group (a terminal's
Ctrl-C), SIGTERM to the supervisor, or SIGKILL of the supervisor (its children then
get the parent-death signal and :mod:`svrobs_cli.guard` bounds their shutdown).
15 s after the stop no process may carry the cycle's value. The scan of one cycle
runs while the next cycle starts. Moments, stops and delays come from one seeded
generator, so every run repeats the same 50 cycles.
"""

from __future__ import annotations

import itertools
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import httpx
import pytest

from tests.integration.stack import ROOT, free_port

from .conftest import RESULTS

pytestmark = [pytest.mark.faults, pytest.mark.timeout(900)]

CYCLES = 50
SEED = 20261201
GRACE = 3.0  # serve --grace: what the children get before they are killed
GONE_WITHIN = 15.0
MARKER = "SVROBS_TEST_STOP_CYCLE"
MOMENTS = ("startup", "idle", "mid-job", "report", "pool-kills", "restart")
STOPS = ("SIGINT to the group", "SIGTERM to the supervisor", "SIGKILL of the supervisor")

# units of ~1-3 s each (a Monte Carlo cost per cell), six of them
LONG = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.1, 0.5, 1.0],
    "N": [60],
    "gamma": [0.05],
    "reps": 10,
    "stages": ["estimate", "bounds", "gain", "cost"],
    "mc_runs": 2000,
    "horizon": 200,
    "seed": 1,
}
TINY = {"systems": ["paper-stable"], "sigma_w": [0.1], "N": [10, 20], "reps": 2, "seed": 2}

SETUP = """
import json
from service.config import get_settings
from svrobs_cli.serve import prepare_dirs, migrate
from service.db.session import session_scope
from service.db import accounts
s = get_settings(); prepare_dirs(s); migrate(s)
with session_scope(s.DATABASE_URL) as db:
    accounts.create_team(db, 'lab')
    accounts.create_user(db, 'lab', 'stop@lab.example', is_admin=True)
    _, key = accounts.create_key(db, 'stop@lab.example')
print(json.dumps({'key': key}))
"""


def plan(rng: random.Random) -> list[tuple[str, str]]:
    """Every (moment, stop) pair two or three times, in a seeded order."""
    pairs = list(itertools.product(MOMENTS, STOPS))
    cycles = pairs * (CYCLES // len(pairs)) + rng.sample(pairs, CYCLES % len(pairs))
    rng.shuffle(cycles)
    return cycles


def _env(var: Path, marker: str | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("SVROBS_")}
    env.update(
        SVROBS_DATABASE_URL=f"sqlite:///{var / 'svrobs.db'}",
        SVROBS_BROKER_URL="filesystem://",
        SVROBS_BROKER_DIR=str(var / "broker"),
        SVROBS_VAR_DIR=str(var),
        SVROBS_TICK_SECONDS="1",
        PYTHONUNBUFFERED="1",
    )
    if marker:
        env[MARKER] = marker
    return env


def marked(value: str) -> list[tuple[int, str]]:
    """(pid, command line) of every live process whose environment holds MARKER=value."""
    needle = f"{MARKER}={value}\0".encode()
    found = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/environ", "rb") as fh:
                if needle not in fh.read():
                    continue  # a zombie's environment is empty: it is not running
            with open(f"/proc/{entry.name}/cmdline", "rb") as fh:
                cmd = fh.read().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:
            continue
        found.append((int(entry.name), cmd[:160]))
    return found


class Cycle:
    def __init__(self, k: int, moment: str, stop: str, root: Path, template: Path, token: str):
        self.k, self.moment, self.stop_how = k, moment, stop
        self.var = root / f"cycle{k:02d}"
        self.var.mkdir()
        for f in template.glob("svrobs.db*"):
            shutil.copy(f, self.var / f.name)
        self.marker = f"{token}-{k}"
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = self.var / "serve.log"
        self.proc: subprocess.Popen | None = None
        self.result: dict = {"cycle": k, "moment": moment, "stop": stop}
        self.checker: threading.Thread | None = None
        self.t_start = self.t_stop = 0.0

    def start(self) -> None:
        with open(self.log, "wb") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "svrobs_cli", "serve", "--port", str(self.port)]
                + ["--grace", f"{GRACE:g}", "--concurrency", "2"],
                cwd=str(ROOT),
                env=_env(self.var, self.marker),
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )

    def text(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_up(self, timeout: float = 120) -> None:
        deadline = time.monotonic() + timeout
        while "svrobs is running" not in self.text():
            assert self.proc.poll() is None, self.text()[-3000:]
            assert time.monotonic() < deadline, self.text()[-3000:]
            time.sleep(0.1)

    def pids(self, name: str) -> list[int]:
        return [
            int(p) for p in re.findall(rf"(?:started|restarted) {name} \(pid (\d+)", self.text())
        ]

    def send_stop(self) -> None:
        self.result["stopped_after_s"] = round(time.monotonic() - self.t_start, 2)
        sig = {"SIGINT to the group": signal.SIGINT, "SIGTERM to the supervisor": signal.SIGTERM}
        if self.stop_how == "SIGINT to the group":
            os.killpg(self.proc.pid, signal.SIGINT)
        else:
            os.kill(self.proc.pid, sig.get(self.stop_how, signal.SIGKILL))
        self.t_stop = time.monotonic()
        self.checker = threading.Thread(target=self._check, daemon=True)
        self.checker.start()

    def _check(self) -> None:
        left: list = []
        while time.monotonic() - self.t_stop < GONE_WITHIN:
            left = marked(self.marker)
            if not left:
                self.result["gone_after_s"] = round(time.monotonic() - self.t_stop, 2)
                break
            time.sleep(0.25)
        self.result["survivors"] = left
        for pid, _cmd in left:  # clean up after a failure, by pid
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        try:
            self.result["supervisor_rc"] = self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.result["supervisor_rc"] = "running"


def _client(cycle: Cycle, key: str) -> httpx.Client:
    return httpx.Client(
        base_url=cycle.url + "/api/v1", headers={"Authorization": f"Bearer {key}"}, timeout=30
    )


def _submit_and_wait(c: httpx.Client, spec: dict, until: tuple[str, ...], timeout=90) -> int:
    r = c.post("/jobs", json=spec)
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    deadline = time.monotonic() + timeout
    while True:
        job = c.get(f"/jobs/{job_id}").json()
        if job["status"] in until:
            return job_id
        assert job["status"] not in ("failed", "cancelled"), job
        assert time.monotonic() < deadline, job
        time.sleep(0.1)


def bring_to(cycle: Cycle, key: str, rng: random.Random) -> None:
    """Take the stack to the cycle's moment (the stop follows at once)."""
    if cycle.moment == "startup":
        time.sleep(rng.uniform(0.3, 3.0))
        return
    cycle.wait_up()
    if cycle.moment == "idle":
        time.sleep(rng.uniform(0.0, 1.0))
    elif cycle.moment == "mid-job":
        with _client(cycle, key) as c:
            _submit_and_wait(c, LONG, ("running",))
        time.sleep(rng.uniform(0.0, 1.0))
    elif cycle.moment == "report":
        with _client(cycle, key) as c:
            job_id = _submit_and_wait(c, TINY, ("succeeded",))

        def fetch():
            try:
                with _client(cycle, key) as c:
                    cycle.result["report_status"] = c.get(f"/jobs/{job_id}/report").status_code
            except httpx.HTTPError as exc:
                cycle.result["report_status"] = type(exc).__name__

        threading.Thread(target=fetch, daemon=True).start()
        time.sleep(rng.uniform(0.1, 1.0))
    elif cycle.moment == "pool-kills":
        with _client(cycle, key) as c:
            _submit_and_wait(c, LONG, ("running",))
        worker = cycle.pids("worker1")[-1]
        kills = 0
        for _ in range(rng.randint(1, 3)):
            pool = [int(p) for p in os.popen(f"pgrep -P {worker}").read().split()]
            if pool:
                os.kill(rng.choice(pool), signal.SIGKILL)
                kills += 1
            time.sleep(rng.uniform(0.1, 0.8))
        cycle.result["pool_kills"] = kills
    elif cycle.moment == "restart":
        os.kill(cycle.pids("worker1")[-1], signal.SIGKILL)
        time.sleep(rng.uniform(0.0, 2.5))


def test_fifty_stop_cycles_leave_no_process(tmp_path):
    rng = random.Random(SEED)
    template = tmp_path / "template"
    template.mkdir()
    out = subprocess.run(
        [sys.executable, "-c", SETUP],
        cwd=str(ROOT),
        env=_env(template),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    key = json.loads(out.stdout.strip().splitlines()[-1])["key"]
    token = uuid.uuid4().hex[:12]

    cycles: list[Cycle] = []
    t0 = time.monotonic()
    try:
        for k, (moment, stop) in enumerate(plan(rng)):
            cycle = Cycle(k, moment, stop, tmp_path, template, token)
            cycles.append(cycle)
            cycle.start()
            cycle.t_start = time.monotonic()
            bring_to(cycle, key, rng)
            cycle.send_stop()
    finally:
        for cycle in cycles:
            if cycle.checker is not None:
                cycle.checker.join(GONE_WITHIN + 15)
            elif cycle.proc is not None and cycle.proc.poll() is None:  # failed before its stop
                os.killpg(cycle.proc.pid, signal.SIGKILL)
                cycle.proc.wait()
                for pid, _cmd in marked(cycle.marker):
                    os.kill(pid, signal.SIGKILL)

    results = [c.result for c in cycles]
    gone = [r["gone_after_s"] for r in results if "gone_after_s" in r]
    RESULTS["stop cycles"] = {
        "cycles": len(results),
        "with survivors 15 s after the stop": sum(1 for r in results if r["survivors"]),
        "gone after (s), max": max(gone, default=None),
        "gone after (s), median": sorted(gone)[len(gone) // 2] if gone else None,
        "pool processes killed": sum(r.get("pool_kills", 0) for r in results),
        "seconds": round(time.monotonic() - t0, 1),
    }
    (tmp_path / "cycles.json").write_text(json.dumps(results, indent=1))
    assert len(results) == CYCLES
    bad = [r for r in results if r["survivors"]]
    assert not bad, json.dumps(bad, indent=1)
    # a supervisor that got SIGINT or SIGTERM once the stack was up stopped cleanly (0)
    clean = [
        r for r in results if r["moment"] != "startup" and r["stop"] != "SIGKILL of the supervisor"
    ]
    assert all(r["supervisor_rc"] == 0 for r in clean), json.dumps(clean, indent=1)
