"""Report columns read as float arrays, put in the row read's order.

The two column reads of a report build that bypass the rows' Python objects (the
binary COPY of :mod:`service.db.report_copy` and the stored blocks of
:mod:`service.db.result_blocks`) give each field as a float64 array in no order,
the coded text fields as indices into a list of their values and ``notes`` as its
``result_notes`` id. :func:`ordered_columns` sorts them into the order of
:func:`service.db.reports.load_columns`'s row read (the cell key; ``system`` and
``estimator`` in the order the database sorts them) and numbers each text field's
codes in order of first appearance, so that every read gives the same columns, bit
for bit (docs/performance.md#the-first-report-of-a-large-job).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
from sqlalchemy import Connection, Integer, any_, bindparam, select
from sqlalchemy.dialects.postgresql import ARRAY
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session

from svrobs_core.report.columns import TEXT_FIELDS

from .models import ResultNote

CODED = tuple(f for f in TEXT_FIELDS if f != "notes")  # text columns read as codes
SORT_KEY = ("system", "sigma_w", "N", "estimator", "gamma_key", "rep")  # the row read's order
_IN_CHUNK = 500  # note ids per IN list on a database without arrays


def psycopg_conn(session: Session):
    """The session's psycopg connection, or None on another driver."""
    conn = session.connection()
    if conn.dialect.name == "postgresql" and conn.dialect.driver == "psycopg":
        return conn.connection.driver_connection
    return None


@contextmanager
def driver_errors(conn: Connection, statement: Any) -> Iterator[None]:
    """psycopg's errors raised as SQLAlchemy's ``DBAPIError`` of ``statement`` (text,
    or a psycopg ``sql`` composition, written out only on an error), as a statement
    run through SQLAlchemy raises them (so the API answers 503 when the database is
    down), the connection invalidated when it was lost."""
    import psycopg

    pg = conn.connection.driver_connection
    try:
        yield
    except psycopg.Error as exc:
        closed = pg is not None and pg.closed
        if closed:
            conn.invalidate(exc)
        text = statement if isinstance(statement, str) else statement.as_string(pg)
        raise DBAPIError.instance(
            text, None, exc, psycopg.Error, connection_invalidated=closed
        ) from exc


def collated(session: Session, values: set) -> list:
    """``values`` (text, and maybe None) in the order of the database's ``ORDER BY``
    of a text column, NULL last: PostgreSQL's collation decides; SQLite's BINARY
    collation compares UTF-8 bytes, the order of Python's ``sorted``."""
    text = [v for v in values if v is not None]
    if len(text) > 1 and session.connection().dialect.name == "postgresql":
        text = list(
            session.connection()
            .exec_driver_sql(
                "SELECT v FROM unnest(CAST(%(v)s AS text[])) AS v ORDER BY v", {"v": text}
            )
            .scalars()
        )
    else:
        text.sort()
    return text + ([None] if None in values else [])


def ordered_columns(
    session: Session, raw: dict[str, np.ndarray], distinct: dict[str, list]
) -> tuple[dict[str, np.ndarray], dict[str, tuple[np.ndarray, list]]]:
    """(fields -> arrays, text field -> (codes, values)) in the row read's order, from
    ``raw``: every scalar field, each coded field as its index into ``distinct[f]``
    (the values in :func:`collated` order), ``notes`` (its id, -1 for none) and
    ``gamma_key``. ``raw`` is emptied as it is read (one field's copy at a time)."""
    order = np.lexsort([raw[f] for f in reversed(SORT_KEY)])
    del raw["gamma_key"]
    data, factors = {}, {}
    for f in list(raw):
        a = raw.pop(f)[order]  # the unsorted array is freed here
        if f in CODED:
            factors[f] = _first_appearance(a.astype(np.int64), distinct[f])
        elif f == "notes":
            factors[f] = _notes(session, a.astype(np.int64))
        else:
            data[f] = a
    return data, factors


def _first_appearance(codes: np.ndarray, values: list) -> tuple[np.ndarray, list]:
    """Codes renumbered in order of first appearance (as ``Columns.codes`` numbers them)."""
    seen, first = np.unique(codes, return_index=True)
    order = seen[np.argsort(first)]
    renumber = np.empty(len(values), dtype=np.int64)
    renumber[order] = np.arange(order.size)
    return renumber[codes], [values[c] for c in order.tolist()]


def _notes(session: Session, note_ids: np.ndarray) -> tuple[np.ndarray, list]:
    """The rows' notes ids (-1: none) -> (codes, texts) as the row read's outer join
    gives them (an id without a text, like -1, is None)."""
    ids = np.unique(note_ids)
    texts = _note_texts(session, ids[ids >= 0].tolist())
    index: dict = {}
    code_of_id = np.array(
        [index.setdefault(texts.get(i), len(index)) for i in ids.tolist()], dtype=np.int64
    )
    return _first_appearance(code_of_id[np.searchsorted(ids, note_ids)], list(index))


def _note_texts(session: Session, known: list[int]) -> dict[int, str]:
    n = ResultNote.__table__.c
    if session.connection().dialect.name == "postgresql":
        ids = bindparam("ids", known, type_=ARRAY(Integer))  # one parameter, any count
        return dict(session.execute(select(n.id, n.text).where(n.id == any_(ids))).all())
    out: dict[int, str] = {}
    for i in range(0, len(known), _IN_CHUNK):
        part = known[i : i + _IN_CHUNK]
        out.update(session.execute(select(n.id, n.text).where(n.id.in_(part))).all())
    return out
