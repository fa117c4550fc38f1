"""Engines and sessions, cached per URL; the one place connections are configured.

SQLite (the embedded default) is shared by the API, the worker and beat
processes, so every connection gets WAL, foreign keys and a busy timeout,
and transactions are begun explicitly: ``BEGIN IMMEDIATE`` for writing
sessions (the default: no SQLITE_BUSY when a reader upgrades to a writer) and
a deferred ``BEGIN`` for read-only sessions (long result streams never block
writers in WAL mode). Savepoints work because pysqlite's own transaction
handling is switched off (SQLAlchemy's documented recipe).
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import orjson
from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

_lock = threading.Lock()
_engines: dict[tuple[str, bool], Engine] = {}
_makers: dict[tuple[str, bool], sessionmaker] = {}

SQLITE_BUSY_TIMEOUT_MS = 30_000
SQLITE_PAGE_SIZE = 8192


def _ensure_sqlite_dir(url: str) -> None:
    u = make_url(url)
    db = u.database
    if db and db != ":memory:" and not db.startswith("file:"):
        parent = os.path.dirname(os.path.abspath(db))
        os.makedirs(parent, exist_ok=True)


def _sqlite_hooks(engine: Engine, immediate: bool) -> None:
    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn, _record):
        dbapi_conn.isolation_level = None  # we emit BEGIN ourselves (savepoints work)
        cur = dbapi_conn.cursor()
        cur.execute(f"PRAGMA busy_timeout = {SQLITE_BUSY_TIMEOUT_MS}")
        cur.execute("PRAGMA foreign_keys = ON")
        # for a new database only (on an existing one the pragma is a no-op): a results
        # row (~380 bytes) is stored whole in one page, so 4 KB pages hold 10 of them
        # (410 B per cell) and 8 KB pages 21 (~390 B per cell: bench/storage.py)
        cur.execute(f"PRAGMA page_size = {SQLITE_PAGE_SIZE}")
        # WAL is stored in the file: set it once (setting it takes a lock; twenty
        # connections opened at once would queue on it, sleeping in the busy handler)
        if cur.execute("PRAGMA journal_mode").fetchone()[0].lower() != "wal":
            cur.execute("PRAGMA journal_mode = WAL")
        cur.execute("PRAGMA synchronous = NORMAL")
        cur.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn):
        conn.exec_driver_sql("BEGIN IMMEDIATE" if immediate else "BEGIN")


def json_text(value: object) -> str:
    """The text of a JSON column's value: orjson's (a unit's summaries are ~40 such
    values; docs/performance.md#the-store-of-a-unit; NaN and infinities as null),
    else what SQLAlchemy's default, ``json.dumps``, writes: for what orjson refuses
    (integers beyond 64 bits, numpy scalars, keys that are not strings)."""
    try:
        return orjson.dumps(value).decode()
    except TypeError:
        return json.dumps(value)


def create_db_engine(url: str, *, write: bool = True) -> Engine:
    """A new engine (not cached); see :func:`get_engine`."""
    if url.startswith("sqlite"):
        _ensure_sqlite_dir(url)
        engine = create_engine(
            url,
            connect_args={"check_same_thread": False, "timeout": SQLITE_BUSY_TIMEOUT_MS / 1000},
            json_serializer=json_text,
        )
        _sqlite_hooks(engine, immediate=write)
        return engine
    kwargs: dict = {"pool_pre_ping": True, "json_serializer": json_text}
    if url.startswith("postgresql"):
        kwargs["connect_args"] = {"connect_timeout": 5}
    return create_engine(url, **kwargs)


def get_engine(url: str, *, write: bool = True) -> Engine:
    """The engine for ``url`` (the caller's settings.DATABASE_URL), one per (URL, write)
    per process."""
    key = (url, write)
    with _lock:
        engine = _engines.get(key)
        if engine is None:
            engine = _engines[key] = create_db_engine(url, write=write)
        return engine


def get_sessionmaker(url: str, *, write: bool = True) -> sessionmaker:
    """A sessionmaker bound to :func:`get_engine` (``expire_on_commit=False``)."""
    engine = get_engine(url, write=write)
    key = (str(engine.url.render_as_string(hide_password=False)), write)
    with _lock:
        maker = _makers.get(key)
        if maker is None:
            maker = _makers[key] = sessionmaker(bind=engine, expire_on_commit=False)
        return maker


@contextmanager
def session_scope(url: str, *, write: bool = True) -> Iterator[Session]:
    """``with session_scope(url) as s: ...`` commits on success, rolls back on error."""
    session = get_sessionmaker(url, write=write)()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def dispose_all() -> None:
    """Dispose every cached engine (tests; after fork)."""
    with _lock:
        for engine in _engines.values():
            engine.dispose()
        _engines.clear()
        _makers.clear()
