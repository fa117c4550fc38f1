"""`svrobs serve` / `make run`: migrate, bootstrap an admin key, run every process.

One command starts the whole embedded stack (or any stack the environment
points at)::

    uvicorn service.app:app                 the REST API on API_HOST:API_PORT
    celery -A worker.celery_app worker      one worker (prefork, one pool process per
                                            CPU plus one, at most 5: DEFAULT_CONCURRENCY)
    celery -A worker.celery_app beat        the scheduler (runs the tick)

``svrobs serve --host H --port P`` picks the API's address (a port in use is one
line naming it, before anything starts). One ``serve`` at a time runs on a state
folder (:mod:`svrobs_cli.serve_lock`): a second one on it, on another port or not,
is one line naming the first one's pid and URL, before anything starts. Once ``/readyz`` answers, a box says
which URL to open, the admin key (first start only) and a first command to run.

Each child is a :class:`svrobs_cli.processes.Child`: its own process group (so a
terminal Ctrl-C reaches only this supervisor, which then stops the children)
and a parent-death signal, run under :mod:`svrobs_cli.guard` (so a SIGKILLed
supervisor leaves nothing running ``grace`` seconds later). A child that exits
is restarted after an exponential backoff (:class:`~svrobs_cli.processes.Supervisor`,
logged); while no worker runs, ``/readyz`` answers 503 (the workers' pid files,
:mod:`service.worker_pids`). Ctrl-C or SIGTERM is forwarded to every child as
SIGTERM; a child still running after ``grace`` seconds gets SIGKILL (its whole
group: the prefork pool too). A second Ctrl-C kills at once.

The helpers (:func:`prepare_dirs`, :func:`migrate`, :func:`child_commands`) are
what the integration tests and ``bench/service.py`` use, so they start exactly
the processes ``serve`` starts.
"""

from __future__ import annotations

import errno
import os
import signal
import socket
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from service import worker_pids
from service.pool_size import default_pool_processes
from service.report_crashes import FILE_NAME as REPORT_CRASHES
from service.report_crashes import CrashRecord
from svrobs_cli import signals as early_signals
from svrobs_cli.errors import CliError
from svrobs_cli.processes import Child, Supervisor, guarded
from svrobs_cli.serve_lock import already_serving, hold_serve_lock, running_serve
from svrobs_core.threads import THREAD_ENV

if TYPE_CHECKING:
    from service.config import Settings

ROOT = Path(__file__).resolve().parent.parent


# --------------------------------------------------------------------------- setup
def _settings() -> Settings:
    """The process's settings, imported at first use: the CLI's REST commands, which
    import this module to register ``serve``, never need them."""
    from service.config import get_settings

    return get_settings()


def var_dir(settings: Settings) -> Path:
    """The state folder, SVROBS_VAR_DIR (``./var`` by default)."""
    return Path(settings.VAR_DIR)


def beat_schedule_file(settings: Settings) -> Path:
    return var_dir(settings) / "celerybeat-schedule"


def broker_folders(settings: Settings) -> list[Path]:
    """The filesystem-broker folders make_celery configured (none for Redis)."""
    if not settings.BROKER_URL.startswith("filesystem"):
        return []
    from service.broker import make_celery

    opts = make_celery(settings).conf.broker_transport_options or {}
    folders = {Path(settings.BROKER_DIR)}
    folders |= {
        Path(v) for k, v in opts.items() if k.endswith("folder") or k.startswith("data_folder")
    }
    return sorted(folders)


def prepare_dirs(settings: Settings) -> None:
    """Create ./var, the SQLite file's folder and the filesystem-broker folders."""
    var_dir(settings).mkdir(parents=True, exist_ok=True)
    if settings.DATABASE_URL.startswith("sqlite"):
        from sqlalchemy.engine import make_url

        db = make_url(settings.DATABASE_URL).database
        if db and db != ":memory:":
            Path(db).resolve().parent.mkdir(parents=True, exist_ok=True)
    for folder in broker_folders(settings):
        folder.mkdir(parents=True, exist_ok=True)


def migrate(settings: Settings | None = None) -> None:
    """``alembic upgrade head`` against settings.DATABASE_URL."""
    from service.db.migrate import upgrade

    upgrade((settings or _settings()).DATABASE_URL)


ADMIN_TEAM = "admin"
ADMIN_EMAIL = "admin@localhost"


def bootstrap_admin(settings: Settings | None = None) -> str | None:
    """First start (no team in the DB): create team ``admin``, its admin user and a key.

    Returns the plaintext key (shown once; only its hash is stored), else None.
    Racing first starts are safe: the team name is unique, the loser gets None.
    """
    from sqlalchemy import func, select
    from sqlalchemy.exc import IntegrityError

    from service.db import accounts
    from service.db.models import Team
    from service.db.session import session_scope
    from svrobs_lab.errors import AdminError

    url = (settings or _settings()).DATABASE_URL
    try:
        with session_scope(url) as s:
            if s.scalar(select(func.count(Team.id))):
                return None
            accounts.create_team(s, ADMIN_TEAM)
            accounts.create_user(s, ADMIN_TEAM, ADMIN_EMAIL, is_admin=True)
            _row, key = accounts.create_key(s, ADMIN_EMAIL, name="bootstrap")
        return key
    except (IntegrityError, AdminError):
        return None


# --------------------------------------------------------------------------- children
def child_env(settings: Settings | None = None, extra: dict | None = None) -> dict:
    """The environment every child gets: ours, single-threaded BLAS, repo on PYTHONPATH."""
    env = dict(os.environ)
    env.update(THREAD_ENV)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])
    )
    env.setdefault("PYTHONUNBUFFERED", "1")
    if settings is not None:
        # children read the same settings the supervisor resolved, with the
        # relative ./var paths made absolute (they must not depend on a cwd)
        for key in ("DATABASE_URL", "BROKER_URL", "BROKER_DIR", "API_HOST", "API_PORT"):
            env[f"SVROBS_{key}"] = str(getattr(settings, key))
        env["SVROBS_BROKER_DIR"] = str(Path(settings.BROKER_DIR).resolve())
        env["SVROBS_VAR_DIR"] = str(Path(settings.VAR_DIR).resolve())
        env["SVROBS_DATABASE_URL"] = _absolute_sqlite(settings.DATABASE_URL)
    env.update(extra or {})
    return env


def _absolute_sqlite(url: str) -> str:
    if not url.startswith("sqlite"):
        return url
    from sqlalchemy.engine import make_url

    u = make_url(url)
    if not u.database or u.database == ":memory:" or u.database.startswith("file:"):
        return url
    return u.set(database=str(Path(u.database).resolve())).render_as_string(hide_password=False)


def api_command(host: str, port: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "uvicorn",
        "service.app:app",
        "--host",
        host,
        "--port",
        str(port),
        "--workers",
        "1",
        "--no-access-log",
        "--http",  # a deadline on each request's headers (slow clients)
        "service.http.request_deadlines:RequestDeadlineProtocol",
    ]


# One pool process per CPU plus one: a unit's claim and store wait on the database
# (SQLite's one writer, PostgreSQL's row locks and COMMIT), and the extra process
# computes meanwhile (bench/service.py, 2 CPUs: 2 -> 3 processes took the Section 6
# grid from 1.66-1.70x to 1.31-1.49x, median 1.39, the core with n_jobs=2 on SQLite). Capped so that
# a big shared machine does not get dozens of ~200 MB numpy/cvxpy processes by surprise.
DEFAULT_CONCURRENCY = default_pool_processes()


def _celery(*argv: str) -> list[str]:
    return [sys.executable, "-m", "celery", "-A", "worker.celery_app", *argv]


def worker_command(
    name: str = "worker1",
    concurrency: int = 1,
    loglevel: str = "info",
    pidfile: Path | None = None,
) -> list[str]:
    return _celery(
        "worker",
        "--concurrency",
        str(concurrency),
        "--pool",
        "prefork",
        "-l",
        loglevel,
        "-n",
        f"{name}@%h",
        "--without-gossip",
        "--without-mingle",
        *(["--pidfile", str(pidfile)] if pidfile else []),
    )


def beat_command(schedule_file: Path, loglevel: str = "info") -> list[str]:
    return _celery(
        "beat",
        "-l",
        loglevel,
        "-s",
        str(schedule_file),
        "-S",
        "worker.beat:TickScheduler",
    )


def pid_dir(settings: Settings) -> Path:
    """Where ``serve``'s workers keep their pid files (read by ``/readyz``)."""
    return var_dir(settings).resolve() / "run"


def child_commands(
    settings: Settings,
    *,
    workers: int = 1,
    concurrency: int = 1,
    beat: bool = True,
    pid_files: bool = False,
) -> list[tuple[str, list[str]]]:
    """``(name, argv)`` of the API, the workers (with ``pid_files``: each writes
    ``pid_dir(settings)/<name>.pid``) and beat."""
    cmds = [("api", api_command(settings.API_HOST, settings.API_PORT))]
    for i in range(workers):
        name = f"worker{i + 1}"
        pidfile = worker_pids.pidfile(pid_dir(settings), name) if pid_files else None
        cmds.append((name, worker_command(name, concurrency, pidfile=pidfile)))
    if beat:
        cmds.append(("beat", beat_command(beat_schedule_file(settings))))
    return cmds


# --------------------------------------------------------------------------- serve
def check_port(host: str, port: int) -> None:
    """Raise :class:`CliError` (one line naming the port and the option) unless the API
    can listen on ``host:port``; nothing has been started when it does."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_STREAM) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
            sock.bind((host, port))
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise CliError(
                f"port {port} is in use; pick another with --port (make run PORT=...)"
            ) from None
        if exc.errno == errno.EACCES:
            raise CliError(
                f"port {port} needs privileges; pick one above 1023 with --port (make run PORT=...)"
            ) from None
        reason = exc.strerror or str(exc)
        raise CliError(
            f"cannot listen on {host}:{port} ({reason}); pick another with --host / --port "
            "(make run HOST=... PORT=...)"
        ) from None


def _browse_host(host: str) -> str:
    """The address to open for an API listening on ``host`` (a wildcard: this host)."""
    if host in ("0.0.0.0", ""):
        return "127.0.0.1"
    if host == "::":
        return "[::1]"
    return f"[{host}]" if ":" in host else host


def _ready(host: str, port: int) -> bool:
    """``GET /readyz`` answers 200 (http.client: no TLS set-up on every poll)."""
    import http.client

    conn = http.client.HTTPConnection(host.strip("[]"), port, timeout=1.0)
    try:
        conn.request("GET", "/readyz")
        return conn.getresponse().status == 200
    except (OSError, http.client.HTTPException):
        return False
    finally:
        conn.close()


def _svrobs_command() -> str:
    """How to call this ``svrobs`` from the working folder (``.venv/bin/svrobs``)."""
    exe = Path(sys.executable).parent / "svrobs"
    if not exe.exists():
        return "svrobs"
    try:
        return str(exe.relative_to(Path.cwd()))
    except ValueError:
        return str(exe)


FIRST_SPEC = '{"systems": ["paper-stable"], "sigma_w": [0.1], "N": [10, 50], "reps": 5}'


def banner(url: str, key: str | None) -> str:
    """The box ``serve`` prints once the stack is up: where to go and what to run
    (ruled above and below only, so a long line wraps without breaking it)."""
    cli = _svrobs_command()
    another = f"{cli} admin create-key {ADMIN_EMAIL}"
    lines = [
        f"svrobs is running: open {url}/  (API docs: {url}/docs)",
        (
            f"admin API key (shown once, keep it): {key}"
            if key
            else f"admin API key: printed on first start (another: {another})"
        ),
        "next, in another terminal:",
        f"  export SVROBS_URL={url} SVROBS_API_KEY={key or 'svr_...'}",
        f"  echo '{FIRST_SPEC}' | {cli} submit - --wait",
        "Ctrl-C here stops everything.",
    ]
    rule = "=" * min(78, max(len(line) for line in lines) + 2)
    return "\n".join([rule, *(f"  {line}" for line in lines), rule])


READY_WAIT_SECONDS = 120.0  # then the box is printed anyway, saying the stack is not ready


def serve(
    settings: Settings | None = None,
    *,
    workers: int = 1,
    concurrency: int = DEFAULT_CONCURRENCY,
    beat: bool = True,
    grace: float = 10.0,
) -> int:
    """Run the stack in the foreground until Ctrl-C or SIGTERM; a child that exits is
    restarted (svrobs_cli.processes.Supervisor). Returns the exit status.

    The signal handlers are set before any work, and a stop that came before them
    (:mod:`svrobs_cli.signals`) counts: a stop during the imports or the migration
    starts nothing (a KeyboardInterrupt raised there can be swallowed by a library's
    bare ``except`` or a finalizer, and the stack would start regardless)."""
    stopping: list[int] = []
    children: list[Child] = []

    def _on_signal(signum, _frame):
        stopping.append(signum)
        if len(stopping) > 1:  # second Ctrl-C: no more waiting
            for c in children:
                c.signal(signal.SIGKILL, group=True)

    old = {s: signal.signal(s, _on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    stopping += early_signals.RECEIVED  # a stop before these handlers were set
    key: str | None = None
    supervisor: Supervisor | None = None
    lock: int | None = None
    announced = False
    try:
        if stopping:
            return 0
        settings = settings or _settings()
        state = var_dir(settings)
        holder = running_serve(state)  # before the port: it may be that serve's port
        if holder is not None:
            raise already_serving(state, holder)
        check_port(settings.API_HOST, settings.API_PORT)
        prepare_dirs(settings)
        browse = _browse_host(settings.API_HOST)
        url = f"http://{browse}:{settings.API_PORT}"
        lock = hold_serve_lock(state, url)
        print(f"svrobs: migrating {_redact(settings.DATABASE_URL)}", flush=True)
        migrate(settings)
        key = bootstrap_admin(settings)
        if key:
            print("svrobs: first start - created team 'admin' and its admin API key", flush=True)
        if stopping:
            return 0
        children += _children(settings, workers=workers, concurrency=concurrency, beat=beat,
                              grace=grace)  # fmt: skip
        supervisor = Supervisor(children, log=lambda line: print(line, file=sys.stderr, flush=True))
        supervisor.start()
        print(f"svrobs: API on {url} - waiting for it and the worker to be ready", flush=True)
        started = time.monotonic()
        while not stopping:
            supervisor.poll()
            if not announced:
                ready = _ready(browse, settings.API_PORT)
                if ready or time.monotonic() - started > READY_WAIT_SECONDS:
                    if not ready:
                        print(
                            f"svrobs: not ready after {READY_WAIT_SECONDS:g} s; see the log above"
                        )
                    print("\n" + banner(url, key) + "\n", flush=True)
                    announced = True
            time.sleep(0.3)
    finally:
        if supervisor is not None or stopping:
            print("svrobs: stopping", flush=True)
        if key and not announced:  # the key is shown once: before it is lost
            print(f"svrobs: admin API key (shown once): {key}", flush=True)
        if supervisor is not None:
            supervisor.stop(grace)
            if settings is not None:  # set before any child started
                # beat's report build cut short by this stop (a second Ctrl-C, or past
                # the grace) did not crash: its mark must not count against its job
                CrashRecord(var_dir(settings) / REPORT_CRASHES).clear()
        if lock is not None:  # after the children stopped: the folder is free again
            os.close(lock)
        for s, h in old.items():
            signal.signal(s, h)
    return 0


def _children(
    settings: Settings, *, workers: int, concurrency: int, beat: bool, grace: float
) -> list[Child]:
    """The stack's processes (API, workers, beat), each under the guard."""
    extra = {}
    if workers > 0:
        pids = pid_dir(settings)
        pids.mkdir(parents=True, exist_ok=True)
        extra["SVROBS_WORKER_PID_DIR"] = str(pids)
    if "SVROBS_WORKER_POOL_PROCESSES" not in os.environ and workers > 0:
        # the fair share follows the pool these workers make (unless set for a
        # pool that spans other hosts too)
        extra["SVROBS_WORKER_POOL_PROCESSES"] = str(workers * concurrency)
    env = child_env(settings, extra)
    children = []
    for name, argv in child_commands(
        settings, workers=workers, concurrency=concurrency, beat=beat, pid_files=workers > 0
    ):
        pidfile = Path(argv[argv.index("--pidfile") + 1]) if "--pidfile" in argv else None
        children.append(Child(name, guarded(argv, grace), env, pidfile=pidfile))
    return children


def _redact(url: str) -> str:
    try:
        from sqlalchemy.engine import make_url

        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # noqa: BLE001 - a log line is written whatever the URL holds
        return url


def serve_command(
    host: str = typer.Option(
        None, "--host", help="the API's address (default: SVROBS_API_HOST, 127.0.0.1)"
    ),
    port: int = typer.Option(
        None, "--port", min=1, max=65535, help="the API's port (default: SVROBS_API_PORT, 8000)"
    ),
    workers: int = typer.Option(1, "--workers", min=0, help="worker processes"),
    concurrency: int = typer.Option(
        DEFAULT_CONCURRENCY,
        "--concurrency",
        min=1,
        help="pool processes per worker (default: one per CPU plus one, at most 5)",
    ),
    no_beat: bool = typer.Option(False, "--no-beat", help="do not start the scheduler"),
    grace: float = typer.Option(
        10.0,
        "--grace",
        min=0.0,
        help="seconds the processes get to stop (then they are killed), also when this one dies",
    ),
) -> None:
    """Migrate, then run API + worker + scheduler (embedded default: SQLite + filesystem broker)."""
    from service.logging_config import configure_logging

    settings = _settings()
    update = {k: v for k, v in (("API_HOST", host), ("API_PORT", port)) if v is not None}
    if update:
        settings = settings.model_copy(update=update)
    configure_logging(settings)
    rc = serve(settings, workers=workers, concurrency=concurrency, beat=not no_beat, grace=grace)
    raise typer.Exit(rc)
