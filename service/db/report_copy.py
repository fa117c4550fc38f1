"""A job's report columns read from PostgreSQL by one binary COPY.

The row read of :func:`service.db.reports.load_columns` hands every value to Python
as an object (on PostgreSQL through a server-side cursor: most of a large job's
first report). Here the server writes each row as fixed-width big-endian float64s
(``COPY (SELECT ...) TO STDOUT (FORMAT BINARY)``): a scalar field as its value or
NaN for NULL, a boolean as 0/1, a text field as the index of its value among the
job's distinct values of that field (read first), ``notes`` as its
``result_notes`` id. numpy reads the stream in blocks of a few MB without one
Python object per value, then sorts the rows into the row read's order (the cell
key; ``system`` and ``estimator`` in the order the database sorts them). The
columns are the same as the row read's, bit for bit
(docs/performance.md#the-first-report-of-a-large-job).
"""

from __future__ import annotations

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from svrobs_core.records import BOOL_FIELDS
from svrobs_core.report.columns import SCALAR_FIELDS

from .models import Result
from .report_order import CODED as _CODED
from .report_order import collated, driver_errors, ordered_columns

_SIGNATURE = b"PGCOPY\n\xff\r\n\x00"
_BLOCK = 1 << 22  # bytes of the stream parsed at once


class StreamChanged(Exception):
    """The stream is not the one expected: a text value the distinct read did not
    see or more rows than counted (a running job's new rows), or not a COPY of
    these fields. The caller reads the rows instead."""


def _distinct(session: Session, job_id: int) -> dict[str, list]:
    """Each coded text field's distinct values in the job, ordered as the database
    orders them (``ORDER BY`` of that column; NULL last)."""
    t = Result.__table__
    combos = session.execute(
        select(*(t.c[f] for f in _CODED)).where(t.c.job_id == job_id).distinct()
    ).all()
    return {f: collated(session, {row[i] for row in combos}) for i, f in enumerate(_CODED)}


def _copy_sql(job_id: int, limit: int, distinct: dict[str, list]):
    """(the COPY statement, its number of fields): the scalars, the coded text
    fields, notes' id and gamma_key, each as a non-NULL float8."""
    from psycopg import sql

    exprs: list[sql.Composable] = []
    for f in SCALAR_FIELDS:
        cast = "{}::int::float8" if f in BOOL_FIELDS else "{}::float8"
        exprs.append(sql.SQL(f"coalesce({cast}, 'NaN')").format(sql.Identifier(f)))
    for f in _CODED:
        col = sql.Identifier(f)
        whens = [
            sql.SQL("WHEN {} IS NULL THEN {}").format(col, sql.Literal(i))
            if v is None
            else sql.SQL("WHEN {} = {} THEN {}").format(col, sql.Literal(v), sql.Literal(i))
            for i, v in enumerate(distinct[f])
        ]
        exprs.append(sql.SQL("coalesce(CASE {} END, -1)::float8").format(sql.SQL(" ").join(whens)))
    exprs.append(sql.SQL("coalesce(notes_id, -1)::float8"))
    exprs.append(sql.SQL("gamma_key::float8"))
    # one row more than counted: with no ORDER BY (a sort the server would have to make),
    # a running job's new rows would give another set of rows than the row read's
    # first ``limit``; the extra row is not read (StreamChanged: the rows are read)
    return sql.SQL(
        "COPY (SELECT {} FROM results WHERE job_id = {} LIMIT {}) TO STDOUT (FORMAT BINARY)"
    ).format(sql.SQL(", ").join(exprs), sql.Literal(job_id), sql.Literal(limit + 1)), len(exprs)


def _read_stream(copy, n_fields: int, limit: int) -> list[np.ndarray]:
    """The COPY's rows as one float array per field (each its own, so that the
    helper fields can be freed once used). The messages are copied into one reused
    buffer (no Python object per row is kept) and parsed whenever it holds a block."""
    row = np.dtype(
        [("n", ">i2")] + [x for i in range(n_fields) for x in ((f"l{i}", ">i4"), (f"v{i}", ">f8"))]
    )
    out = [np.empty(limit) for _ in range(n_fields)]
    buf = bytearray(_BLOCK)
    fill, at, header, whole = 0, 0, True, True

    def parse(start: int, end: int) -> int:
        """Copy the whole rows of buf[start:end] out; -> where the first row left starts."""
        nonlocal at, whole
        k = min((end - start) // row.itemsize, limit - at)
        a = np.frombuffer(buf, dtype=row, count=k, offset=start)
        lengths = np.array([a[f"l{i}"] for i in range(n_fields)])
        if k and ((a["n"] != n_fields).any() or (lengths != 8).any()):
            whole = False  # a NULL where none can be: not the stream of these rows
        if whole:
            for i in range(n_fields):
                out[i][at : at + k] = a[f"v{i}"]
            at += k
        return start + k * row.itemsize

    # the whole stream is read even when it is not as expected: leaving a COPY early
    # cancels it, and the session's transaction with it
    for data in copy:
        n = len(data)
        if fill + n > len(buf):
            buf.extend(bytes(fill + n - len(buf)))
        buf[fill : fill + n] = data
        fill += n
        if fill < _BLOCK:
            continue
        start = 0
        if header:
            start = _header_size(buf, fill)
            if start > fill:
                continue  # the header is not all here yet
            header = False
        used = parse(start, fill)
        buf[: fill - used] = buf[used:fill]
        fill -= used
    start = _header_size(buf, fill) if header else 0
    end = fill - 2  # the trailer: -1 as a field count
    if start > end or buf[end:fill] != b"\xff\xff" or parse(start, end) != end or not whole:
        raise StreamChanged
    return [a[:at] for a in out]


def _header_size(buf: bytearray, fill: int) -> int:
    """Bytes of the binary COPY header at the start of ``buf[:fill]`` (signature,
    flags, extension length, extension); more than ``fill`` until it is all there."""
    if fill < 19:
        return 19
    if buf[: len(_SIGNATURE)] != _SIGNATURE:
        return fill + 1  # not a COPY stream: nothing of it is parsed (and the end check fails)
    return 19 + int.from_bytes(buf[15:19], "big")


def copy_columns(session: Session, job_id: int, limit: int):
    """(fields -> arrays, text field -> (codes, values)) of at most ``limit`` rows of
    the job, in the row read's order; raises :class:`StreamChanged` when the rows
    changed between the reads."""
    distinct = _distinct(session, job_id)
    query, n_fields = _copy_sql(job_id, limit, distinct)
    conn = session.connection()
    pg = conn.connection.driver_connection
    assert pg is not None  # an open connection (session.connection() began it)
    names = [*SCALAR_FIELDS, *_CODED, "notes", "gamma_key"]
    with driver_errors(conn, query), pg.cursor() as cur, cur.copy(query) as copy:
        raw = dict(zip(names, _read_stream(copy, n_fields, limit), strict=True))
    if any((raw[f] < 0).any() for f in _CODED):
        raise StreamChanged  # a text value the distinct read did not see
    return ordered_columns(session, raw, distinct)
