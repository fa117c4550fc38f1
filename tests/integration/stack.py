"""Real-process stacks shared by the integration and the fault tests.

:class:`Stack` migrates a database, creates a team and key, and starts uvicorn,
celery workers and beat with the exact commands ``svrobs_cli.serve`` uses
(``svrobs_cli.serve.child_commands``); teardown terminates every child, then kills
its process group: no orphans. Logs are under the stack's folder and their
tails are printed when a wait times out.
"""

from __future__ import annotations

import fcntl
import functools
import json
import math
import os
import secrets
import socket
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

import httpx

ROOT = Path(__file__).resolve().parents[2]

from svrobs_cli.processes import Child, stop_all
from svrobs_cli.serve import api_command, beat_command, child_env, worker_command
from svrobs_core import parse_spec, run_spec

PG_URL = os.environ.get("SVROBS_TEST_DATABASE_URL")
REDIS_URL = os.environ.get("SVROBS_TEST_BROKER_URL")
API = "/api/v1"
READY_TIMEOUT = 90.0


# Ports for test servers come from a block of their own per test process, below the
# kernel's ephemeral range (32768-60999), so that an outgoing connection's source port
# cannot take a port between this check and the server's bind (a port asked of the
# kernel with bind(0) could be handed out again). A process claims the first block no
# other process on the machine holds (an flock on the block's file, held while the
# process lives): the xdist workers of one suite, a second suite or `make test-faults`
# beside it never draw the same ports.
_PORT_FIRST = 20000
_PORT_BLOCK = 1000
_PORT_BLOCKS = 12  # 20000-31999
_next_port: list[int] = []  # the next port to try, once the block is claimed
_held_locks: list = []  # the claimed block's lock file, open while this process lives


@functools.cache
def _claim_block() -> int:
    """The first port of this process's block (its lock file stays open while we live)."""
    folder = Path(os.environ.get("TMPDIR", "/tmp")) / "svrobs-test-ports"
    folder.mkdir(exist_ok=True)
    for k in range(_PORT_BLOCKS):
        lock = open(folder / f"block-{k}.lock", "w")  # noqa: SIM115 - held while we live
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            lock.close()
            continue
        _held_locks.append(lock)
        base = _PORT_FIRST + k * _PORT_BLOCK
        _next_port.append(base + os.getpid() % _PORT_BLOCK)
        return base
    raise RuntimeError(f"all {_PORT_BLOCKS} test port blocks are held ({folder})")


def free_port() -> int:
    """A loopback port that nothing listens on, from this process's block."""
    base = _claim_block()
    for _ in range(_PORT_BLOCK):
        port = _next_port[0]
        _next_port[0] = base + (port + 1 - base) % _PORT_BLOCK
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError(f"no free port in {base}-{base + _PORT_BLOCK - 1}")


class PortTaken(AssertionError):
    """The server could not bind its port: another process took it after the check."""


def _with_search_path(url: str, schema: str) -> str:
    parts = urlsplit(url)
    q = parts.query + ("&" if parts.query else "") + f"options=-csearch_path%3D{schema}"
    return urlunsplit(parts._replace(query=q))


def _tail(path: Path, n: int = 60) -> str:
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    return "\n".join(lines[-n:])


class Stack:
    """A stack's processes and settings. ``kind`` is ``embedded`` or ``pg`` (PostgreSQL +
    Redis at ``pg_url`` / ``redis_url``, default the SVROBS_TEST_* URLs; the fault
    tests pass their private servers' URLs). ``extra_env`` is added to every child's
    environment."""

    def __init__(
        self,
        kind: str,
        root: Path,
        *,
        pg_url: str | None = None,
        redis_url: str | None = None,
        extra_env: dict | None = None,
    ):
        self.kind = kind
        self.root = root
        self.pg_url = pg_url or PG_URL
        self.redis_url = redis_url or REDIS_URL
        self.logs = root / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.children: dict[str, Child] = {}
        self.schema: str | None = None
        self.key: str = ""
        self.base_url = ""
        env = {k: v for k, v in os.environ.items() if not k.startswith("SVROBS_")}
        if kind == "embedded":
            env.update(
                SVROBS_DATABASE_URL=f"sqlite:///{root / 'svrobs.db'}",
                SVROBS_BROKER_URL="filesystem://",
                SVROBS_BROKER_DIR=str(root / "broker"),
            )
        else:
            self.schema = f"it_{os.getpid()}_{secrets.token_hex(3)}"
            env.update(
                SVROBS_DATABASE_URL=_with_search_path(self.pg_url, self.schema),
                SVROBS_BROKER_URL=self.redis_url,
                SVROBS_BROKER_DIR=str(root / "broker"),
            )
        env.update(SVROBS_TASK_TIME_LIMIT="300", SVROBS_UNIT_LEASE_SECONDS="360")
        # the schedule tests step through due times a minute apart
        env.update(SVROBS_MIN_SCHEDULE_INTERVAL_SECONDS="60")
        env.update(SVROBS_VAR_DIR=str(root))
        env.update(extra_env or {})
        self.env = child_env(None, env)
        # child_env starts from os.environ: drop any SVROBS_* the developer has set
        for k in [k for k in self.env if k.startswith("SVROBS_") and k not in env]:
            del self.env[k]

    # ----------------------------------------------------------------- setup
    def setup(self) -> None:
        if self.kind == "pg":
            import sqlalchemy as sa

            engine = sa.create_engine(self.pg_url)
            with engine.begin() as c:
                c.exec_driver_sql(f'CREATE SCHEMA "{self.schema}"')
            engine.dispose()
            self.flush_redis()
        # what `svrobs serve` runs first, here in this process with the stack's settings
        from service.config import Settings
        from svrobs_cli.serve import migrate, prepare_dirs

        ours = {
            k.removeprefix("SVROBS_"): v for k, v in self.env.items() if k.startswith("SVROBS_")
        }
        self.settings = Settings(**ours)
        prepare_dirs(self.settings)
        migrate(self.settings)
        self.key = self.team_key("lab")

    def team_key(self, team: str) -> str:
        """A new team of the stack's database, its user ``it@<team>.example`` and that
        user's API key (made in this process)."""
        from sqlalchemy.orm import Session

        from service.db import accounts
        from service.db.session import create_db_engine

        engine = create_db_engine(self.settings.DATABASE_URL)
        try:
            with Session(engine) as db, db.begin():
                accounts.create_team(db, team)
                accounts.create_user(db, team, f"it@{team}.example")
                _, key = accounts.create_key(db, f"it@{team}.example")
        finally:
            engine.dispose()
        return key

    def teardown(self) -> None:
        stop_all(list(self.children.values()), grace=10)
        self.children.clear()
        if self.kind == "pg":
            import sqlalchemy as sa

            engine = sa.create_engine(self.pg_url)
            with engine.begin() as c:
                c.exec_driver_sql(f'DROP SCHEMA IF EXISTS "{self.schema}" CASCADE')
            engine.dispose()
            self.flush_redis()

    def flush_redis(self) -> None:
        import redis

        r = redis.Redis.from_url(self.redis_url)
        r.flushdb()
        r.close()

    def python(self, code: str, *, env: dict | None = None, timeout: float = 60) -> str:
        """Run ``code`` in a fresh interpreter with the stack's environment."""
        proc = subprocess.run(
            [sys.executable, "-c", code],
            cwd=str(ROOT),
            env={**self.env, **(env or {})},
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )
        if proc.returncode != 0:
            raise AssertionError(f"subprocess failed ({proc.returncode}):\n{proc.stderr[-4000:]}")
        return proc.stdout

    # ----------------------------------------------------------------- processes
    def start(self, name: str, argv: list[str], env: dict | None = None) -> Child:
        assert name not in self.children or self.children[name].poll() is not None, name
        log = self.logs / f"{name}.log"
        if log.exists():  # a restart: keep the old log aside, wait_log reads the new one
            n = len(list(self.logs.glob(f"{name}.*.log"))) + 1
            log.rename(self.logs / f"{name}.{n}.log")
        child = Child(name, argv, {**self.env, **(env or {})}, log=log)
        self.children[name] = child.start()
        return child

    def stop(self, name: str, grace: float = 10) -> None:
        child = self.children.pop(name, None)
        if child is not None:
            child.stop(grace)

    def start_api(self, name: str = "api", env: dict | None = None, wait: str = "/readyz") -> str:
        for attempt in range(3):
            port = free_port()
            self.start(name, api_command("127.0.0.1", port), env)
            url = f"http://127.0.0.1:{port}"
            try:
                self.wait_http(url + wait, name)
            except PortTaken:
                if attempt == 2:
                    raise
                continue  # taken between the check and the bind: another port
            if name == "api":
                self.base_url = url
            return url
        raise AssertionError("unreachable")

    def start_worker(
        self,
        name: str = "worker1",
        concurrency: int = 1,
        env: dict | None = None,
        *,
        wait: bool = True,
    ) -> Child:
        child = self.start(name, worker_command(name, concurrency), env)
        if wait:
            self.wait_log(name, "ready.")
        return child

    def start_api_and_worker(self, concurrency: int = 1) -> None:
        """The API and ``worker1``, started at once (each waits on its own imports)."""
        self.start_worker(concurrency=concurrency, wait=False)
        self.start_api()
        self.wait_log("worker1", "ready.")

    def start_beat(
        self, name: str = "beat", tick_seconds: float = 1.0, env: dict | None = None
    ) -> Child:
        env = {"SVROBS_TICK_SECONDS": str(tick_seconds), **(env or {})}
        return self.start(name, beat_command(self.root / f"{name}-schedule"), env)

    def wait_http(self, url: str, name: str, timeout: float = READY_TIMEOUT) -> None:
        """Until the uvicorn child ``name`` has bound the port of ``url`` (its log says
        so: a 200 from another process on that port does not count) and answers 200.
        PortTaken when it could not bind."""
        deadline = time.monotonic() + timeout
        last = None
        bound = f"running on http://127.0.0.1:{urlsplit(url).port} "
        log = self.logs / f"{name}.log"
        while time.monotonic() < deadline:
            child = self.children[name]
            if child.poll() is not None:
                tail = self.log_tail(name)
                error = PortTaken if "address already in use" in tail else AssertionError
                raise error(f"{name} exited ({child.poll()}):\n{tail}")
            if not log.exists() or bound not in log.read_text(errors="replace"):
                last = "not bound yet"
                time.sleep(0.2)
                continue
            try:
                r = httpx.get(url, timeout=2)
                if r.status_code == 200:
                    return
                last = f"{r.status_code} {r.text[:300]}"
            except httpx.HTTPError as exc:
                last = repr(exc)
            time.sleep(0.2)
        raise AssertionError(f"{url} not ready in {timeout}s: {last}\n{self.log_tail(name)}")

    def wait_log(
        self, name: str, text: str, timeout: float = READY_TIMEOUT, count: int = 1
    ) -> None:
        deadline = time.monotonic() + timeout
        path = self.logs / f"{name}.log"
        while time.monotonic() < deadline:
            child = self.children[name]
            if child.poll() is not None:
                raise AssertionError(f"{name} exited ({child.poll()}):\n{self.log_tail(name)}")
            if path.exists() and path.read_text(errors="replace").count(text) >= count:
                return
            time.sleep(0.2)
        raise AssertionError(
            f"{name}: {text!r} not logged {count}x in {timeout}s:\n{self.log_tail(name)}"
        )

    def log_tail(self, *names: str, n: int = 60) -> str:
        names = names or tuple(p.stem for p in sorted(self.logs.glob("*.log")))
        return "\n".join(f"--- {nm}.log ---\n{_tail(self.logs / f'{nm}.log', n)}" for nm in names)

    # ----------------------------------------------------------------- REST
    def client(self, base_url: str | None = None) -> httpx.Client:
        return httpx.Client(
            base_url=(base_url or self.base_url) + API,
            timeout=30,
            headers={"Authorization": f"Bearer {self.key}"},
        )

    def wait_job(
        self,
        client: httpx.Client,
        job_id,
        *,
        statuses=("succeeded", "failed", "cancelled"),
        timeout: float = 120.0,
    ) -> dict:
        deadline = time.monotonic() + timeout
        job = None
        while time.monotonic() < deadline:
            r = client.get(f"/jobs/{job_id}")
            assert r.status_code == 200, r.text
            job = r.json()
            if job["status"] in statuses:
                return job
            time.sleep(0.25)
        raise AssertionError(f"job {job_id} not {statuses} in {timeout}s: {job}\n{self.log_tail()}")


# --------------------------------------------------------------------------- records


def cell_key(r: dict) -> tuple:
    return (
        r["system"],
        r["sigma_w"],
        r["N"],
        r["estimator"],
        -1.0 if r["gamma"] is None else r["gamma"],
        r["rep"],
    )


def in_process_records(spec: dict) -> dict[tuple, dict]:
    """The core run in this process, through a JSON round trip (what the API serves)."""
    recs = [r for batch in run_spec(parse_spec(spec)) for r in batch]
    return {cell_key(r): json.loads(json.dumps(r, allow_nan=False)) for r in recs}


def same(a, b, path="") -> list[str]:
    """Exact, type-aware equality: floats bit for bit (after the JSON round trip),
    bool never equal to a number; int vs float only when the values are equal."""
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: length {len(a)} != {len(b)}"]
        return [m for i, (x, y) in enumerate(zip(a, b)) for m in same(x, y, f"{path}[{i}]")]
    if isinstance(a, bool) or isinstance(b, bool):
        return [] if type(a) is type(b) and a == b else [f"{path}: {a!r} != {b!r}"]
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        if float(a) == float(b) and math.copysign(1, float(a)) == math.copysign(1, float(b)):
            return []
        return [f"{path}: {a!r} != {b!r}"]
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


def fetch_jsonl(client, job_id) -> list[dict]:
    r = client.get(f"/jobs/{job_id}/results", params={"format": "jsonl"})
    assert r.status_code == 200, r.text
    return [json.loads(line) for line in r.text.splitlines() if line.strip()]


def submit(client, spec: dict, **extra) -> dict:
    r = client.post("/jobs", json={**spec, **extra})
    assert r.status_code == 202, r.text
    return r.json()
