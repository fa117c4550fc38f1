"""Benchmark: a unit's claim / compute / store in one process (CPU seconds of this
process, ``time.process_time``, and the store's wall time), the grid of
``bench/service.py``, on SQLite or, with ``--pg``, on a fresh database of the
PostgreSQL server of ``SVROBS_BENCH_DATABASE_URL`` or ``SVROBS_TEST_DATABASE_URL``
(dropped afterwards; the server's own CPU is not counted); ``-p`` adds a profile of the store
(docs/performance.md#the-store-of-a-unit).

    PYTHONPATH=. OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/unit_store.py [UNITS] [-p] [--pg]
"""

import cProfile
import os
import pstats
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from sqlalchemy import select

from bench.pg_private import bench_pg_url, private_database
from bench.service import GRID
from service.db import accounts, jobs, migrate
from service.db.models import WorkUnit
from service.db.session import session_scope
from service.db.units import complete_unit, start_unit
from svrobs_lab.units import compute_unit


@contextmanager
def database(pg: bool) -> Iterator[str]:
    """A fresh database URL: SQLite in a temporary folder, or a private PostgreSQL
    database (``bench.pg_private``, dropped at the end)."""
    if not pg:
        yield f"sqlite:///{tempfile.mkdtemp()}/p.db"
        return
    base = bench_pg_url()
    if base is None:
        sys.exit("--pg: set SVROBS_BENCH_DATABASE_URL or SVROBS_TEST_DATABASE_URL")
    with private_database(base, "svrobs_bench_unit_store") as url:
        yield url


def main() -> None:
    with database("--pg" in sys.argv) as url:
        run(url)


def run(url: str) -> None:
    migrate.upgrade(url)
    with session_scope(url) as s:
        t = accounts.create_team(s, "t")
        u = accounts.create_user(s, "t", "a@t.example")
        s.flush()
        job, _ = jobs.create_job(s, team_id=t.id, user_id=u.id, spec=GRID)
        s.flush()
        jid = job.id
    with session_scope(url) as s:
        uids = list(
            s.scalars(select(WorkUnit.id).where(WorkUnit.job_id == jid).order_by(WorkUnit.id))
        )
    n = int(sys.argv[1]) if len(sys.argv) > 1 and sys.argv[1].isdigit() else 12
    prof = cProfile.Profile() if "-p" in sys.argv else None
    tc = tp = ts = ws = 0.0
    for uid in uids[:n]:
        c0 = time.process_time()
        with session_scope(url) as s:
            spec, payload = start_unit(s, uid, "w", 60, max_attempts=0)
        c1 = time.process_time()
        res, _ = compute_unit(lambda **k: session_scope(url, **k), spec, payload)
        c2 = time.process_time()
        w2 = time.perf_counter()
        if prof:
            prof.enable()
        with session_scope(url) as s:
            complete_unit(s, uid, res)
        if prof:
            prof.disable()
        c3 = time.process_time()
        ws += time.perf_counter() - w2
        tc += c1 - c0
        tp += c2 - c1
        ts += c3 - c2
    print(
        f"{url.split(':')[0]}, {n} units: claim {1000 * tc / n:.1f} ms, compute {1000 * tp / n:.1f}"
        f" ms, store {1000 * ts / n:.1f} ms (wall {1000 * ws / n:.1f} ms),"
        f" (claim+store)/compute {(tc + ts) / tp:.1%}"
    )
    if prof:
        pstats.Stats(prof).sort_stats("cumulative").print_stats(45)


if __name__ == "__main__":
    main()
