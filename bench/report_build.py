"""The steps of a first report, in one process: the column read and the rendering.

    .venv/bin/python bench/report_build.py                      # a new SQLite database
    .venv/bin/python bench/report_build.py --db URL --job 1     # a job stored before
    .venv/bin/python bench/report_build.py --pg                 # a private PostgreSQL one

Without ``--db`` it stores ``bench/reads.py``'s synthetic job of ``--cells`` rows
(625,050 by default) through the real write path, in a temporary SQLite database
or (``--pg``) a private PostgreSQL database on the server of
``SVROBS_BENCH_DATABASE_URL`` / ``SVROBS_TEST_DATABASE_URL`` (``bench.pg_private``). Then, ``--runs``
times, it reads the job's columns (``service.db.reports.load_columns``) and
renders its page (``svrobs_lab.report_html.job_report_html``), and prints the wall
and CPU seconds of each step and a sha256 of the page (the same on every run; for
the same cells on SQLite and PostgreSQL the pages differ only in the job's
provenance). The imports a fresh API process would pay
at its first report (matplotlib) are done before the first run, and so is the start
of the helper processes that draw the figures (``svrobs_lab.figure_pool``; its time
is printed; ``SVROBS_REPORT_RENDER_PROCESSES=0`` draws them in this process). The
CPU printed is this process's: the helpers' is not in it.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.reads import PAPER_CELLS, bench_spec, load_job  # noqa: E402


def timed(fn, *args):
    w, c = time.perf_counter(), time.process_time()
    out = fn(*args)
    return out, time.perf_counter() - w, time.process_time() - c


def measure(db_url: str, job_id: int, runs: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401 - the imports, before the first run

    from service.config import get_settings
    from service.db.models import Job
    from service.db.reports import load_columns
    from service.db.session import get_sessionmaker
    from svrobs_lab.figure_pool import configure, warm
    from svrobs_lab.reports import JobSnapshot, _render

    helpers = get_settings().REPORT_RENDER_PROCESSES
    configure(helpers)  # as the API app and beat do
    (started, start_s, _) = timed(warm, helpers)
    if started:
        print(f"  {helpers} helper processes drawing the figures, started in {start_s:.2f} s")
    else:
        print("  the figures drawn in this process (SVROBS_REPORT_RENDER_PROCESSES=0)")
    make = get_sessionmaker(db_url, write=False)
    for run in range(runs):
        with make() as s:
            snap = JobSnapshot.of(s.get(Job, job_id))
            cols, read_w, read_c = timed(load_columns, s, job_id)
        html, draw_w, draw_c = timed(_render, snap, cols)
        digest = hashlib.sha256(html.encode()).hexdigest()[:16]
        print(
            f"  run {run + 1}: {len(cols):,} cells; read {read_w:5.2f} s ({read_c:5.2f} CPU), "
            f"render {draw_w:5.2f} s ({draw_c:5.2f} CPU), total {read_w + draw_w:5.2f} s; "
            f"page {len(html) / 1e3:.0f} kB sha256 {digest}"
        )
        del cols, html


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--db", help="a database holding the job (with --job)")
    ap.add_argument("--job", type=int, default=1)
    ap.add_argument("--pg", action="store_true", help="store the job in a private PostgreSQL db")
    ap.add_argument("--cells", type=int, default=PAPER_CELLS)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args(argv)
    if args.db:
        measure(args.db, args.job, args.runs)
        return 0
    if args.pg:
        from bench.pg_private import bench_pg_url, private_database

        base = bench_pg_url()
        if base is None:
            ap.error("--pg needs SVROBS_BENCH_DATABASE_URL or SVROBS_TEST_DATABASE_URL")
        with private_database(base, "svrobs_bench_report_build") as url:
            _, job_id, rows, s = load_job(url, bench_spec(args.cells))
            print(f"PostgreSQL: {rows:,} rows stored in {s:.1f} s")
            measure(url, job_id, args.runs)
        return 0
    with tempfile.TemporaryDirectory(prefix="svrobs-report-build-") as d:
        url = f"sqlite:///{Path(d) / 'svrobs.db'}"
        _, job_id, rows, s = load_job(url, bench_spec(args.cells))
        print(f"SQLite: {rows:,} rows stored in {s:.1f} s")
        measure(url, job_id, args.runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
