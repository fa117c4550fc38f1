"""Stored reports (``job_reports``) and the bounded read the report is built from.

A finished job never changes, so its report is built once (by a worker when the
tick sees the job finished, or at the first request) and then served as stored,
until the page's layout changes: a stored report records the layout it was built
with, and one of another layout is built again from the job's rows
(:func:`servable_report`), except when those rows were pruned (``jobs.pruned_at``):
then the stored page is the only copy and is served as it is.
The build reads only the fields the report uses (``REPORT_FIELDS``) into numpy
arrays, with no record dicts, and no ``A_hat``/``B_hat`` above
``MATRIX_CELLS_LIMIT`` cells (as ``svrobs reproduce`` does; the figures that need
them say "no data"). Without the matrices, the columns come from the blocks the
units wrote with their rows (:mod:`service.db.result_blocks`) when they make up
the job, else on PostgreSQL from one binary COPY of fixed-width floats
(:mod:`service.db.report_copy`); otherwise the rows are read from the cursor in
chunks of ``CHUNK``, each text field factorised as it is read
(docs/performance.md#the-first-report-of-a-large-job).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from svrobs_core.report.columns import (
    COLUMN_MATRIX_FIELDS,
    SCALAR_FIELDS,
    TEXT_FIELDS,
    Columns,
    FirstCodes,
)

from .models import JOB_ACTIVE, Job, JobReport, Result, utcnow
from .report_copy import StreamChanged, copy_columns
from .report_order import SORT_KEY, ordered_columns, psycopg_conn
from .result_blocks import block_columns, drop_blocks
from .results_store import NOTES, job_codec

log = logging.getLogger(__name__)

CHUNK = 5_000
MATRIX_CELLS_LIMIT = 200_000


def stored_report(session: Session, job_id: int) -> JobReport | None:
    return session.get(JobReport, job_id)


def servable_report(session: Session, job_id: int, layout: int) -> JobReport | None:
    """The job's stored report if it is served as stored: built with ``layout``, or
    of any layout once the job's rows were pruned (the stored page is then the only
    copy); None when the report is to be built (again) from the rows."""
    row = session.get(JobReport, job_id)
    if row is None or row.layout == layout:
        return row
    pruned = session.scalar(select(Job.pruned_at).where(Job.id == job_id))
    return row if pruned is not None else None


def is_final(job: Job) -> bool:
    """A finished job (succeeded, failed or cancelled): its report can be stored."""
    return job.status not in JOB_ACTIVE


def store_report(
    session: Session, job_id: int, html: str, n_records: int, layout: int
) -> JobReport:
    """Store (or replace) a finished job's report, built with page layout ``layout``;
    its blocks (:mod:`service.db.result_blocks`) are no longer needed and go."""
    drop_blocks(session, job_id)
    row = session.get(JobReport, job_id)
    if row is None:
        row = JobReport(job_id=job_id, html=html, n_records=n_records, layout=layout)
        session.add(row)
    else:
        row.html, row.n_records, row.built_at = html, n_records, utcnow()
        row.layout = layout
    session.flush()
    return row


def jobs_without_report(
    session: Session,
    limit: int,
    *,
    layout: int,
    finished_after=None,
    skip: Sequence[int] = (),
) -> list[int]:
    """Finished jobs that have cell rows and no stored report of page layout
    ``layout`` (none, or one of another layout: :func:`servable_report`), finished
    after ``finished_after`` if given, not in ``skip``; newest first."""
    current = select(JobReport.job_id).where(JobReport.job_id == Job.id, JobReport.layout == layout)
    q = (
        select(Job.id)
        .where(Job.status.not_in(JOB_ACTIVE), Job.pruned_at.is_(None), Job.n_cells > 0)
        .where(~current.exists())
        .order_by(Job.finished_at.desc())
        .limit(limit)
    )
    if finished_after is not None:
        q = q.where(Job.finished_at >= finished_after)
    if skip:
        q = q.where(Job.id.not_in(list(skip)))
    return list(session.scalars(q))


def _matrix_block(values: list, shape: tuple[int, int] | None) -> tuple[np.ndarray, tuple | None]:
    """Decoded matrices (nested lists, None for null) -> (k, a, b) floats, NaN where
    missing."""
    if shape is None:
        shape = next((np.shape(v) for v in values if v is not None), None)
    if shape is None or len(shape) != 2:
        return np.full((len(values), 0, 0), np.nan), None
    out = np.full((len(values), *shape), np.nan)
    for i, v in enumerate(values):
        if v is not None and np.shape(v) == shape:
            out[i] = np.asarray(v, dtype=float)  # None entries -> nan
    return out, shape


def _chunks(session: Session, q) -> Iterator[Sequence[Sequence]]:
    """The rows of ``q`` in chunks of ``CHUNK``. On SQLite straight from the driver's
    cursor (plain tuples: a third less time than SQLAlchemy's rows; booleans as 0/1);
    on PostgreSQL through a server-side cursor (``yield_per``)."""
    conn = session.connection()
    if conn.dialect.name != "sqlite":
        yield from session.execute(q.execution_options(yield_per=CHUNK)).partitions(CHUNK)
        return
    compiled = q.compile(dialect=conn.dialect)
    params = [compiled.params[name] for name in compiled.positiontup or ()]
    driver = conn.connection.driver_connection
    assert driver is not None  # an open connection (session.connection() began it)
    cur = driver.cursor()
    try:
        cur.execute(str(compiled), params)
        while part := cur.fetchmany(CHUNK):
            yield part
    finally:
        cur.close()


def _counted_cells(session: Session, job_id: int) -> int | None:
    """The job's rows as its units counted them (``cells_done``, written in the
    transaction that writes a unit's rows and block), or None after its rows were
    pruned: the blocks are checked against it instead of a count of the rows,
    which reads every row's index entry (0.12-0.15 s on PostgreSQL at 625,050
    cells, docs/performance.md#the-first-report-of-a-large-job)."""
    row = session.execute(
        select(Job.cells_done, Job.pruned_at).where(Job.id == job_id)
    ).one_or_none()
    return None if row is None or row.pruned_at is not None else int(row.cells_done)


def load_columns(session: Session, job_id: int, *, matrices: bool | None = None) -> Columns:
    """The job's stored records as report :class:`Columns` (the same values as
    ``Columns.from_records`` of its records), read in chunks. ``matrices``: load
    ``A_hat``/``B_hat`` (default: when the job has at most MATRIX_CELLS_LIMIT rows)."""
    t = Result.__table__
    counted = _counted_cells(session, job_id)
    if counted and (matrices is False or (matrices is None and counted > MATRIX_CELLS_LIMIT)):
        stored = block_columns(session, job_id, counted)
        if stored is not None:  # the blocks make up the job: its rows are not counted
            return _columns(*ordered_columns(session, *stored))
    n = session.scalar(select(func.count()).select_from(t).where(t.c.job_id == job_id)) or 0
    if matrices is None:
        matrices = n <= MATRIX_CELLS_LIMIT
    mats = COLUMN_MATRIX_FIELDS if matrices else ()
    if n and not mats and n != counted:
        stored = block_columns(session, job_id, n)
        if stored is not None:
            return _columns(*ordered_columns(session, *stored))
    if n and not mats and psycopg_conn(session) is not None:
        try:
            copied, factors = copy_columns(session, job_id, n)
        except StreamChanged:  # a running job's rows changed meanwhile: read the rows
            log.info("job %s: its rows changed during the COPY read; reading rows", job_id)
        else:
            return _columns(copied, factors)
    codec = job_codec(session, job_id)
    text_cols = [NOTES.c.text if f == "notes" else t.c[f] for f in TEXT_FIELDS]
    cols = [t.c[f] for f in SCALAR_FIELDS] + text_cols + [t.c[f] for f in mats]
    data: dict[str, np.ndarray] = {f: np.full(n, np.nan) for f in SCALAR_FIELDS}
    blocks: dict[str, list] = {f: [] for f in mats}
    shapes: dict[str, tuple | None] = dict.fromkeys(mats)
    order = [t.c[f] for f in SORT_KEY]
    # at most the rows counted (a running job may be writing more meanwhile)
    q = (
        select(*cols)
        .select_from(t.outerjoin(NOTES, t.c.notes_id == NOTES.c.id))
        .where(t.c.job_id == job_id)
        .order_by(*order)
        .limit(n)
    )
    ns, nt = len(SCALAR_FIELDS), len(TEXT_FIELDS)
    sig = SCALAR_FIELDS.index("sigma_w")
    # each text field factorised as it is read (Columns.codes: codes in order of first
    # appearance), so each distinct text is one str object and is never factorised again
    firsts = {f: FirstCodes() for f in TEXT_FIELDS}
    codes = {f: np.empty(n, dtype=np.int64) for f in TEXT_FIELDS}
    at = 0
    for part in _chunks(session, q):
        k = len(part)
        rows = np.array([tuple(r) for r in part], dtype=object)  # (k, columns)
        # floats; None -> NaN, booleans (0/1 on SQLite) -> 0.0/1.0
        scalars = rows[:, :ns].astype(float)
        for i, f in enumerate(SCALAR_FIELDS):
            data[f][at : at + k] = scalars[:, i]
        for i, f in enumerate(TEXT_FIELDS):
            codes[f][at : at + k] = firsts[f].encode(rows[:, ns + i])
        if mats:
            systems = list(rows[:, ns + TEXT_FIELDS.index("system")])
            sigmas = scalars[:, sig].tolist()
        for i, f in enumerate(mats):
            decoded = codec.decode_matrices(systems, sigmas, f, list(rows[:, ns + nt + i]))
            block, shapes[f] = _matrix_block(decoded, shapes[f])
            blocks[f].append(block)
        at += k
    factors = {f: (codes[f][:at], list(firsts[f])) for f in TEXT_FIELDS}
    data = {f: a[:at] for f, a in data.items()}
    for f in mats:
        shape = shapes[f]
        data[f] = (
            np.concatenate(
                [
                    b if b.shape[1:] == shape else np.full((len(b), *shape), np.nan)
                    for b in blocks[f]
                ]
            )
            if shape is not None
            else np.full((at, 0, 0), np.nan)
        )
    return _columns(data, factors)


def _columns(data: dict[str, np.ndarray], factors: dict[str, tuple]) -> Columns:
    """Columns of the scalar (and matrix) arrays and the factorised text fields."""
    for f, (codes, distinct) in factors.items():
        data[f] = np.array([*distinct, None], dtype=object)[:-1][codes]
    return Columns(data, len(data["rep"]), codes=factors)
