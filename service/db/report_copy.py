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
from svrobs_core.report.columns import SCALAR_FIELDS, TEXT_FIELDS

from .models import Result, ResultNote

_CODED = tuple(f for f in TEXT_FIELDS if f != "notes")  # text columns sent as codes
_SIGNATURE = b"PGCOPY\n\xff\r\n\x00"
_BLOCK = 1 << 22  # bytes of the stream parsed at once
SORT_KEY = ("system", "sigma_w", "N", "estimator", "gamma_key", "rep")  # the row read's order


class StreamChanged(Exception):
    """A row the distinct values read first do not cover (a running job's new rows):
    the caller reads the rows instead."""


def _distinct(session: Session, job_id: int) -> dict[str, list]:
    """Each coded text field's distinct values in the job, ordered as the database
    orders them (``ORDER BY`` of that column; NULL last)."""
    t = Result.__table__
    combos = session.execute(
        select(*(t.c[f] for f in _CODED)).where(t.c.job_id == job_id).distinct()
    ).all()
    out = {}
    for i, f in enumerate(_CODED):
        values = {row[i] for row in combos}
        text = [v for v in values if v is not None]
        if len(text) > 1:  # the database's collation decides, as in the row read's ORDER BY
            text = list(
                session.connection()
                .exec_driver_sql(
                    "SELECT v FROM unnest(CAST(%(v)s AS text[])) AS v ORDER BY v", {"v": text}
                )
                .scalars()
            )
        out[f] = text + ([None] if None in values else [])
    return out


def _copy_sql(job_id: int, limit: int, distinct: dict[str, list]):
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
    return sql.SQL(
        "COPY (SELECT {} FROM results WHERE job_id = {} LIMIT {}) TO STDOUT (FORMAT BINARY)"
    ).format(sql.SQL(", ").join(exprs), sql.Literal(job_id), sql.Literal(limit)), len(exprs)


def _read_stream(copy, n_fields: int, limit: int) -> np.ndarray:
    """The COPY's rows as an (n_fields, rows) float array."""
    row = np.dtype(
        [("n", ">i2")] + [x for i in range(n_fields) for x in ((f"l{i}", ">i4"), (f"v{i}", ">f8"))]
    )
    out = np.empty((n_fields, limit))
    at, rest, parts, size, header, whole = 0, b"", [], 0, True, True

    def parse(buf: bytes) -> bytes:
        nonlocal at, whole
        k = min(len(buf) // row.itemsize, limit - at)
        a = np.frombuffer(buf, dtype=row, count=k)
        lengths = np.array([a[f"l{i}"] for i in range(n_fields)])
        if k and ((a["n"] != n_fields).any() or (lengths != 8).any()):
            whole = False  # a NULL where none can be: not the stream of these rows
        if whole:
            for i in range(n_fields):
                out[i, at : at + k] = a[f"v{i}"]
            at += k
        return buf[k * row.itemsize :]

    # the whole stream is read even when it is not as expected: leaving a COPY early
    # cancels it, and the session's transaction with it
    for data in copy:
        parts.append(bytes(data))
        size += len(data)
        if size < _BLOCK:
            continue
        buf, parts, size = rest + b"".join(parts), [], 0
        if header:
            if len(buf) < _header_size(buf):
                rest = buf  # the header is not all here yet
                continue
            buf, header = buf[_header_size(buf) :], False
        rest = parse(buf)
    buf = rest + b"".join(parts)
    if header:
        buf = buf[_header_size(buf) :]
    if buf[-2:] != b"\xff\xff" or parse(buf[:-2]) or not whole:
        raise StreamChanged
    return out[:, :at]


def _header_size(buf: bytes) -> int:
    """Bytes of the binary COPY header at the start of ``buf`` (signature, flags,
    extension length, extension)."""
    if len(buf) < 19:
        return 19
    if buf[: len(_SIGNATURE)] != _SIGNATURE:
        return len(buf)  # not a COPY stream: nothing of it is parsed (and the end check fails)
    return 19 + int.from_bytes(buf[15:19], "big")


def _first_appearance(codes: np.ndarray, values: list) -> tuple[np.ndarray, list]:
    """Codes renumbered in order of first appearance (as ``Columns.codes`` numbers them)."""
    seen, first = np.unique(codes, return_index=True)
    order = seen[np.argsort(first)]
    renumber = np.empty(len(values), dtype=np.int64)
    renumber[order] = np.arange(order.size)
    return renumber[codes], [values[c] for c in order.tolist()]


def copy_columns(session: Session, job_id: int, limit: int):
    """(fields -> arrays, text field -> (codes, values)) of at most ``limit`` rows of
    the job, in the row read's order; raises :class:`StreamChanged` when the rows
    changed between the reads."""
    distinct = _distinct(session, job_id)
    query, n_fields = _copy_sql(job_id, limit, distinct)
    pg = session.connection().connection.driver_connection
    assert pg is not None  # an open connection (session.connection() began it)
    with pg.cursor() as cur, cur.copy(query) as copy:
        raw = _read_stream(copy, n_fields, limit)
    ns = len(SCALAR_FIELDS)
    field_row = {f: i for i, f in enumerate(SCALAR_FIELDS)}
    field_row.update({f: ns + i for i, f in enumerate(_CODED)})
    field_row.update({"notes": n_fields - 2, "gamma_key": n_fields - 1})
    if raw.shape[1] and (raw[ns : ns + len(_CODED)] < 0).any():
        raise StreamChanged  # a text value the distinct read did not see
    order = np.lexsort([raw[field_row[f]] for f in reversed(SORT_KEY)])
    for i in range(n_fields):  # in place, one field at a time (no second copy of all)
        raw[i] = raw[i][order]
    data = {f: raw[field_row[f]] for f in SCALAR_FIELDS}
    factors = {
        f: _first_appearance(raw[field_row[f]].astype(np.int64), distinct[f]) for f in _CODED
    }
    factors["notes"] = _notes(session, raw[field_row["notes"]].astype(np.int64))
    return data, factors


def _notes(session: Session, note_ids: np.ndarray) -> tuple[np.ndarray, list]:
    """The rows' notes ids (-1: none) -> (codes, texts) as the row read's outer join
    gives them (an id without a text, like -1, is None)."""
    ids = np.unique(note_ids)
    known = ids[ids >= 0].tolist()
    texts = dict(
        session.execute(
            select(ResultNote.id, ResultNote.text).where(ResultNote.id.in_(known))
        ).all()
    )
    index: dict = {}
    code_of_id = np.array(
        [index.setdefault(texts.get(i), len(index)) for i in ids.tolist()], dtype=np.int64
    )
    return _first_appearance(code_of_id[np.searchsorted(ids, note_ids)], list(index))
