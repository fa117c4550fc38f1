"""Bytes per stored cell, before (the JSON format of migrations 0001-0002) and after (head's).

    python bench/storage.py                 # SQLite, and PostgreSQL if configured
    python bench/storage.py --reps 10       # quicker

A job of the paper's grid with stages estimate, bounds, gain and cost (``--grid
e4``: 2 systems x sigma_w 1 x N x svr at 4 gammas x 200 reps, as the preset's
E3/E4 that hold 86% of its cells; ``section6``: x sigma_w {0.1, 1, 10} x {ols,
svr} x 45 reps as E1/E2; the Monte Carlo J for rep < 10) is computed by the core and
stored through the real write path (``units.complete_unit`` of each unit's
:class:`UnitResult`), on SQLite and on PostgreSQL (``SVROBS_BENCH_DATABASE_URL``,
else ``SVROBS_TEST_DATABASE_URL``: a private database is created and dropped).
Then it prints bytes per cell

* SQLite: the file size after ``VACUUM`` / cells, and of it the pages of the
  results tables (``results``, ``result_notes``, ``result_constants`` and their
  indexes; the rest is summaries, jobs, units and one page per empty table);
* PostgreSQL: ``pg_total_relation_size`` of the same tables / cells, after
  ``VACUUM FULL``;

for the compact format (migrations 0006, 0007; SQLite with 8 KB pages), and for the
same rows after ``alembic downgrade 0002``
(the migration converts them back to the JSON format): "before" vs "after".
The target is at most 400 bytes per cell.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from sqlalchemy import create_engine, text

from bench.pg_private import bench_pg_url, private_database
from service.db import accounts, jobs, units
from service.db.migrate import downgrade, upgrade
from service.db.session import dispose_all, session_scope
from svrobs_core.parsing import parse_spec
from svrobs_core.runner import run_unit_result


def grid(name: str, reps: int, n_values: int) -> dict:
    """The paper's grid with stages estimate, bounds, gain and cost: ``e4`` as the
    preset's E3/E4 (svr at 4 gammas, sigma_w 1; 540,000 of its 625,050 cells),
    ``section6`` as its E1/E2 (3 sigma_w, ols and svr)."""
    step = max(10, (450 - 10) // max(1, n_values - 1) // 10 * 10)
    out = {
        "systems": ["paper-stable", "paper-unstable"],
        "sigma_w": [1.0] if name == "e4" else [0.1, 1.0, 10.0],
        "N": {"start": 10, "stop": 10 + step * (n_values - 1), "step": step},
        "gamma": [0.005, 0.01, 0.05, 0.1],
        "estimators": ["svr"] if name == "e4" else ["ols", "svr"],
        "reps": reps,
        "stages": ["estimate", "bounds", "gain", "cost"],
        "mc_reps": 10,
        "mc_runs": 100,
        "horizon": 200,
        "seed": 0,
    }
    return out


def load(url: str, spec_dict: dict) -> int:
    """Create a job of ``spec_dict`` and store every unit as a worker would."""
    with session_scope(url) as s:
        team = accounts.create_team(s, "bench")
        job, _ = jobs.create_job(
            s, team_id=team.id, user_id=None, spec=spec_dict, max_cells=10**7, max_active_jobs=0
        )
        job_id = job.id
    spec = parse_spec(spec_dict)
    with session_scope(url) as s:
        ids = jobs.unit_ids_of_job(s, job_id)
    for uid in ids:
        with session_scope(url) as s:
            spec_json, payload = units.start_unit(s, uid, "bench", 600, max_attempts=0)
        result = run_unit_result(spec, payload)
        with session_scope(url) as s:
            units.complete_unit(s, uid, result)
    with session_scope(url) as s:
        return s.execute(text("SELECT count(*) FROM results")).scalar()


RESULT_TABLES = ("results", "result_notes", "result_constants")


def sqlite_bytes(path: Path) -> tuple[int, int]:
    """(the file's size, of it the pages of the results tables and their indexes),
    after VACUUM."""
    dispose_all()
    eng = create_engine(f"sqlite:///{path}")
    with eng.connect() as c:
        c.exec_driver_sql("PRAGMA wal_checkpoint(TRUNCATE)")
        c.exec_driver_sql("VACUUM")
        tables = ", ".join(f"'{t}'" for t in RESULT_TABLES)
        pages = c.exec_driver_sql(
            f"SELECT sum(pgsize) FROM dbstat WHERE name IN ({tables}) OR name IN "
            f"(SELECT name FROM sqlite_schema WHERE tbl_name IN ({tables}))"
        ).scalar()
    eng.dispose()
    return path.stat().st_size, pages


def pg_bytes(url: str) -> tuple[int, int]:
    """(results + result_notes total size, of it the indexes), after VACUUM FULL."""
    dispose_all()
    eng = create_engine(url, isolation_level="AUTOCOMMIT")
    with eng.connect() as c:
        tables = [t for t in RESULT_TABLES if c.scalar(text(f"SELECT to_regclass('{t}')"))]
        total = idx = 0
        for t in tables:
            c.exec_driver_sql(f"VACUUM FULL ANALYZE {t}")
            total += c.scalar(text(f"SELECT pg_total_relation_size('{t}')"))
            idx += c.scalar(text(f"SELECT pg_indexes_size('{t}')"))
    eng.dispose()
    return total, idx


def measure(label: str, url: str, spec: dict, sizes) -> tuple[int, tuple, tuple]:
    """Store the job at head, ``sizes()`` (compact), downgrade to 0002, ``sizes()`` again
    -> (cells, sizes before, sizes after)."""
    upgrade(url)
    t0 = time.perf_counter()
    n = load(url, spec)
    print(f"{label}: stored {n} cells in {time.perf_counter() - t0:.1f} s")
    after = sizes()
    downgrade(url, "0002")
    return n, sizes(), after


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--grid", choices=("e4", "section6"), default="e4")
    ap.add_argument("--reps", type=int, default=None, help="default: 200 (e4), 45 (section6)")
    ap.add_argument("--n-values", type=int, default=2, help="how many N of the grid")
    ap.add_argument("--stacks", default="sqlite,pg")
    args = ap.parse_args()
    reps = args.reps or (200 if args.grid == "e4" else 45)
    spec = grid(args.grid, reps, args.n_values)
    cells = parse_spec(spec).n_cells
    print(f"job: {cells} cells (grid {args.grid}, stages {', '.join(spec['stages'])}, reps {reps})")
    out = {}
    if "sqlite" in args.stacks:
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / "bench.db"
            n, before, after = measure(
                "sqlite", f"sqlite:///{path}", spec, lambda: sqlite_bytes(path)
            )
            out["sqlite (file / cell)"] = (before[0] / n, after[0] / n)
            out["sqlite (results tables / cell)"] = (before[1] / n, after[1] / n)
    base = bench_pg_url()
    if "pg" in args.stacks and base:
        with private_database(base, "svrobs_storage") as url:
            n, before, after = measure("pg", url, spec, lambda: pg_bytes(url))
            out["pg (results tables / cell)"] = (before[0] / n, after[0] / n)
            out["pg  of which indexes"] = (before[1] / n, after[1] / n)
    print(f"\n{'bytes per cell':<28} {'before (JSON)':>14} {'after (head)':>13}")
    for k, (b, a) in out.items():
        print(f"{k:<28} {b:>14.0f} {a:>13.0f}")
    print("target: <= 400 bytes per cell")


if __name__ == "__main__":
    main()
