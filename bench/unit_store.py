"""Benchmark: a unit's claim / compute / store in one process on SQLite (CPU seconds,
``time.process_time``), the grid of ``bench/service.py``; ``-p`` adds a profile of the
store (docs/performance.md#the-store-of-a-unit).

    PYTHONPATH=. OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/unit_store.py [UNITS] [-p]
"""

import cProfile
import os
import pstats
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from sqlalchemy import select

from bench.service import GRID
from service.db import accounts, jobs, migrate
from service.db.models import WorkUnit
from service.db.session import session_scope
from service.db.units import complete_unit, start_unit
from svrobs_lab.units import compute_unit


def main() -> None:
    d = tempfile.mkdtemp()
    url = f"sqlite:///{d}/p.db"
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
    tc = tp = ts = 0.0
    for uid in uids[:n]:
        c0 = time.process_time()
        with session_scope(url) as s:
            spec, payload = start_unit(s, uid, "w", 60, max_attempts=0)
        c1 = time.process_time()
        res, _ = compute_unit(lambda **k: session_scope(url, **k), spec, payload)
        c2 = time.process_time()
        if prof:
            prof.enable()
        with session_scope(url) as s:
            complete_unit(s, uid, res)
        if prof:
            prof.disable()
        c3 = time.process_time()
        tc += c1 - c0
        tp += c2 - c1
        ts += c3 - c2
    print(
        f"{n} units: claim {1000 * tc / n:.1f} ms, compute {1000 * tp / n:.1f} ms, store {1000 * ts / n:.1f} ms, (claim+store)/compute {(tc + ts) / tp:.1%}"
    )
    if prof:
        pstats.Stats(prof).sort_stats("cumulative").print_stats(45)


if __name__ == "__main__":
    main()
