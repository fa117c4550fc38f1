"""`svrobs serve` / `make run`: migrate, bootstrap an admin key, run every process.

One command starts the whole embedded stack (or any stack the environment
points at)::

    uvicorn service.app:app                 the REST API on API_HOST:API_PORT
    celery -A worker.celery_app worker      one worker (prefork, one pool process per
                                            CPU plus one, at most 5: DEFAULT_CONCURRENCY)
    celery -A worker.celery_app beat        the scheduler (runs the tick)

Each child is a :class:`svrobs_cli.processes.Child`: its own process group (so a
terminal Ctrl-C reaches only this supervisor, which then stops the children in
order) and a parent-death signal (so a SIGKILLed supervisor leaves no orphans).
Ctrl-C or SIGTERM is forwarded to every child as SIGTERM; a child still running
after ``grace`` seconds gets SIGKILL (its whole group: the prefork pool too). A
second Ctrl-C kills at once. If any child exits on its own, the others are
stopped and ``serve`` returns non-zero.

The helpers (:func:`prepare_dirs`, :func:`migrate`, :func:`child_commands`) are
what the integration tests and ``bench/service.py`` use, so they start exactly
the processes ``serve`` starts.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import typer

from service.config import Settings, get_settings
from svrobs_cli.processes import Child, stop_all
from svrobs_core.threads import THREAD_ENV

ROOT = Path(__file__).resolve().parent.parent


# --------------------------------------------------------------------------- setup
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

    upgrade((settings or get_settings()).DATABASE_URL)


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

    url = (settings or get_settings()).DATABASE_URL
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
    ]


# One pool process per CPU plus one: a unit's claim and store wait on the database
# (SQLite's one writer, PostgreSQL's row locks and COMMIT), and the extra process
# computes meanwhile (bench/service.py, 2 CPUs: 2 -> 3 processes took the Section 6
# grid from 1.66-1.70x to 1.31-1.49x, median 1.39, the core with n_jobs=2 on SQLite). Capped so that
# a big shared machine does not get dozens of ~200 MB numpy/cvxpy processes by surprise.
DEFAULT_CONCURRENCY = max(1, min((os.cpu_count() or 1) + 1, 5))


def _celery(*argv: str) -> list[str]:
    return [sys.executable, "-m", "celery", "-A", "worker.celery_app", *argv]


def worker_command(
    name: str = "worker1", concurrency: int = 1, loglevel: str = "info"
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


def child_commands(
    settings: Settings, *, workers: int = 1, concurrency: int = 1, beat: bool = True
) -> list[tuple[str, list[str]]]:
    cmds = [("api", api_command(settings.API_HOST, settings.API_PORT))]
    cmds += [
        (f"worker{i + 1}", worker_command(f"worker{i + 1}", concurrency)) for i in range(workers)
    ]
    if beat:
        cmds.append(("beat", beat_command(beat_schedule_file(settings))))
    return cmds


# --------------------------------------------------------------------------- serve
def serve(
    settings: Settings | None = None,
    *,
    workers: int = 1,
    concurrency: int = DEFAULT_CONCURRENCY,
    beat: bool = True,
    grace: float = 10.0,
) -> int:
    """Run the stack in the foreground until Ctrl-C/SIGTERM or a child dies."""
    settings = settings or get_settings()
    prepare_dirs(settings)
    print(f"svrobs: migrating {_redact(settings.DATABASE_URL)}", flush=True)
    migrate(settings)
    key = bootstrap_admin(settings)
    if key:
        print("svrobs: first start - created team 'admin'. Admin API key (shown once):", flush=True)
        print(f"\n    {key}\n", flush=True)

    env = child_env(settings)
    children = [
        Child(name, argv, env)
        for name, argv in child_commands(
            settings, workers=workers, concurrency=concurrency, beat=beat
        )
    ]

    stopping: list[int] = []

    def _on_signal(signum, _frame):
        stopping.append(signum)
        if len(stopping) > 1:  # second Ctrl-C: no more waiting
            for c in children:
                c.signal(signal.SIGKILL, group=True)

    old = {s: signal.signal(s, _on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    rc = 0
    try:
        for c in children:
            c.start()
            print(f"svrobs: started {c.name} (pid {c.pid})", flush=True)
        print(
            f"svrobs: API on http://{settings.API_HOST}:{settings.API_PORT} "
            f"(docs at /docs); Ctrl-C stops everything",
            flush=True,
        )
        while not stopping:
            dead = [c for c in children if c.poll() is not None]
            if dead:
                for c in dead:
                    print(
                        f"svrobs: {c.name} exited with code {c.poll()}; stopping",
                        file=sys.stderr,
                        flush=True,
                    )
                rc = 1
                break
            time.sleep(0.3)
    finally:
        print("svrobs: stopping", flush=True)
        stop_all(children, grace=grace)
        for s, h in old.items():
            signal.signal(s, h)
    return rc


def _redact(url: str) -> str:
    try:
        from sqlalchemy.engine import make_url

        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # noqa: BLE001 - a log line is written whatever the URL holds
        return url


def serve_command(
    workers: int = typer.Option(1, "--workers", help="worker processes"),
    concurrency: int = typer.Option(
        DEFAULT_CONCURRENCY,
        "--concurrency",
        help="pool processes per worker (default: one per CPU plus one, at most 5)",
    ),
    no_beat: bool = typer.Option(False, "--no-beat", help="do not start the scheduler"),
) -> None:
    """Migrate, then run API + worker + scheduler (embedded default: SQLite + filesystem broker)."""
    from service.logging_config import configure_logging

    settings = get_settings()
    configure_logging(settings)
    rc = serve(settings, workers=workers, concurrency=concurrency, beat=not no_beat)
    raise typer.Exit(rc)
