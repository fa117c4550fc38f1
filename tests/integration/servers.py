"""Private, throw-away PostgreSQL and Redis servers for tests that stop and restart them.

:class:`PrivateRedis` runs ``redis-server`` on a spare 127.0.0.1 port without
persistence; :class:`PrivatePostgres` runs ``initdb`` into a temporary folder and
the postmaster in the foreground on a spare 127.0.0.1 port (as the ``postgres``
OS user when running as root: initdb refuses root). Both run in their own
process group with a parent-death signal, and ``stop``/``close`` kill the group:
the machine's own servers are never touched and nothing is left behind.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
import time
from glob import glob
from pathlib import Path

from svrobs_cli.processes import Child, deathsig, kill_group

from .stack import free_port

START_TIMEOUT = 30.0


def _pg_bindir() -> Path | None:
    env = os.environ.get("SVROBS_PG_BINDIR")
    cands = [env] if env else sorted(glob("/usr/lib/postgresql/*/bin"), reverse=True)
    cands += [os.path.dirname(p) for p in [shutil.which("initdb")] if p]
    for c in cands:
        if c and all(
            os.access(os.path.join(c, b), os.X_OK) for b in ("initdb", "pg_ctl", "postgres")
        ):
            return Path(c)
    return None


PG_BINDIR = _pg_bindir()
REDIS_SERVER = shutil.which("redis-server")


def _wait(pred, timeout: float, what: str, step: float = 0.1):
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        try:
            if pred():
                return
        except Exception as exc:  # noqa: BLE001 - retried until the deadline
            last = exc
        time.sleep(step)
    raise AssertionError(f"{what} not reached in {timeout}s (last error: {last!r})")


# --------------------------------------------------------------------------- redis
class PrivateRedis:
    """``redis-server`` on a spare 127.0.0.1 port, no RDB, no AOF (a restart loses the
    queue: the worst case for the relay)."""

    def __init__(self, root: Path):
        self.dir = root
        self.dir.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.child: Child | None = None
        self.starts = 0

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def running(self) -> bool:
        return self.child is not None and self.child.poll() is None

    def ping(self) -> bool:
        import redis

        r = redis.Redis(
            host="127.0.0.1", port=self.port, socket_timeout=1, socket_connect_timeout=1
        )
        try:
            return bool(r.ping())
        finally:
            r.close()

    def start(self) -> None:
        assert not self.running()
        self.starts += 1
        argv = [
            REDIS_SERVER,
            "--port",
            str(self.port),
            "--bind",
            "127.0.0.1",
            "--save",
            "",
            "--appendonly",
            "no",
            "--daemonize",
            "no",
            "--dir",
            str(self.dir),
            "--protected-mode",
            "yes",
        ]
        self.child = Child(
            "redis", argv, dict(os.environ), log=self.dir / "redis.log", cwd=self.dir
        ).start()
        _wait(lambda: self.child.poll() is None and self.ping(), START_TIMEOUT, "redis ping")

    def stop(self) -> None:
        if self.child is not None:
            self.child.stop(grace=5)  # SIGTERM (no save configured), then SIGKILL the group
            self.child = None

    def restart(self, down: float) -> float:
        """Stop, stay down ``down`` s, start on the same port; returns the seconds down."""
        t0 = time.monotonic()
        self.stop()
        time.sleep(down)
        self.start()
        return time.monotonic() - t0


# --------------------------------------------------------------------------- postgres
PG_DIR_PREFIX = "svrobs-faults-pg-"


def _remove_stale_clusters(min_age: float = 600.0) -> None:
    """Folders a killed test run left behind (its postmaster died with it): no
    ``postmaster.pid``, or one naming a dead process, and untouched for 10 min."""
    for d in Path(tempfile.gettempdir()).glob(PG_DIR_PREFIX + "*"):
        try:
            if time.time() - d.stat().st_mtime < min_age:
                continue
            pidfile = d / "data" / "postmaster.pid"
            if pidfile.exists():
                pid = int(pidfile.read_text().split()[0])
                try:
                    os.kill(pid, 0)
                    continue  # still running: another run's cluster
                except ProcessLookupError:
                    pass
            shutil.rmtree(d, ignore_errors=True)
        except (OSError, ValueError, IndexError):
            continue


class PrivatePostgres:
    """A throw-away cluster: ``initdb`` into a temporary folder, the postmaster in the
    foreground (own process group, parent-death signal) on a spare 127.0.0.1 port,
    socket in the same folder. ``stop`` is ``pg_ctl stop -m fast``."""

    def __init__(self):
        assert PG_BINDIR is not None
        self.bindir = PG_BINDIR
        self.user = None
        if os.geteuid() == 0:
            import pwd

            self.user = pwd.getpwnam("postgres")
        # not under pytest's tmp_path: its root-only folders cannot be entered by `postgres`
        _remove_stale_clusters()
        self.dir = Path(tempfile.mkdtemp(prefix=PG_DIR_PREFIX))
        if self.user is not None:
            os.chown(self.dir, self.user.pw_uid, self.user.pw_gid)
        os.chmod(self.dir, 0o700)
        self.data = self.dir / "data"
        self.port = free_port()
        self.proc: subprocess.Popen | None = None
        self.starts = 0

    @property
    def url(self) -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/postgres"

    def _run(self, argv: list[str], timeout: float = 60) -> subprocess.CompletedProcess:
        out = subprocess.run(
            argv,
            cwd=str(self.dir),
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
            **self._as_user(),
        )
        if out.returncode != 0:
            raise AssertionError(f"{argv} failed ({out.returncode}):\n{out.stdout}\n{out.stderr}")
        return out

    def _as_user(self) -> dict:
        if self.user is None:
            return {}
        return {"user": self.user.pw_uid, "group": self.user.pw_gid, "extra_groups": []}

    def init(self) -> None:
        self._run(
            [
                str(self.bindir / "initdb"),
                "-D",
                str(self.data),
                "-A",
                "trust",
                "-U",
                "postgres",
                "-E",
                "UTF8",
                "--no-sync",
                "--no-instructions",
            ]
        )

    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def ready(self) -> bool:
        import psycopg

        with psycopg.connect(
            host="127.0.0.1", port=self.port, user="postgres", dbname="postgres", connect_timeout=2
        ) as c:
            return c.execute("SELECT 1").fetchone() == (1,)

    def start(self) -> None:
        assert not self.running()
        self.starts += 1
        argv = [
            str(self.bindir / "postgres"),
            "-D",
            str(self.data),
            "-p",
            str(self.port),
            "-k",
            str(self.dir),
            "-c",
            "listen_addresses=127.0.0.1",
            # a test cluster: durability off (a fast shutdown still checkpoints)
            "-c",
            "fsync=off",
            "-c",
            "synchronous_commit=off",
            "-c",
            "full_page_writes=off",
            "-c",
            "max_connections=200",
        ]
        log = open(self.dir / "postgres.log", "ab")  # noqa: SIM115 - handed to the child
        try:
            self.proc = subprocess.Popen(
                argv,
                cwd=str(self.dir),
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                preexec_fn=deathsig(signal.SIGQUIT),
                **self._as_user(),  # noqa: PLW1509
            )
        finally:
            log.close()
        _wait(
            lambda: self.proc.poll() is None and self.ready(),
            START_TIMEOUT,
            f"postgres ready on {self.port}",
        )

    def stop(self, mode: str = "fast") -> None:
        """``pg_ctl stop -m <mode>`` (waits), then make sure the process group is gone."""
        if not self.running():
            return
        try:
            self._run(
                [
                    str(self.bindir / "pg_ctl"),
                    "-D",
                    str(self.data),
                    "-m",
                    mode,
                    "-w",
                    "-t",
                    "30",
                    "stop",
                ],
                timeout=40,
            )
        finally:
            self._kill_group()

    def _kill_group(self) -> None:
        if self.proc is None:
            return
        try:
            self.proc.wait(10)  # the postmaster's own shutdown first
        except subprocess.TimeoutExpired:
            pass
        kill_group(self.proc)

    def restart(self, down: float) -> float:
        t0 = time.monotonic()
        self.stop("fast")
        time.sleep(down)
        self.start()
        return time.monotonic() - t0

    def close(self) -> None:
        try:
            self.stop("immediate")
        except Exception:  # noqa: BLE001 - the group is killed anyway
            self._kill_group()
        shutil.rmtree(self.dir, ignore_errors=True)

    def log_tail(self, n: int = 40) -> str:
        try:
            return "\n".join(
                (self.dir / "postgres.log").read_text(errors="replace").splitlines()[-n:]
            )
        except OSError:
            return ""
