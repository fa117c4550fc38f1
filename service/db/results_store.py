"""Writing section 10 records into ``results`` (SPEC section 10): one upsert on the
cell key, from record dicts or straight from a unit's column arrays; and a
stored row back to a record (:func:`row_to_record`).

The hot write path of the worker. Rows are tuples in table-column order,
matrices and ``seed_key`` as their JSON text, with no per-row SQLAlchemy
parameter processing: on SQLite one DBAPI ``executemany`` of an ``INSERT ..
ON CONFLICT (cell key) DO UPDATE``; on PostgreSQL a COPY into a temporary
table and one ``INSERT .. SELECT .. ON CONFLICT``. Values are cleaned as the
ORM would store them: NaN/inf -> NULL, numpy scalars -> Python, JSON ``null``
for an absent matrix.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Sequence

import numpy as np
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import Session

from svrobs_core.records import BOOL_FIELDS, RECORD_FIELDS, json_value
from svrobs_core.unit_result import UnitResult

from .models import OLS_GAMMA_KEY, RESULT_MATRIX_FIELDS, RESULT_SCALAR_FIELDS, Result

KEY_COLUMNS = ("job_id", "system", "sigma_w", "N", "estimator", "gamma_key", "rep")
JSON_COLUMNS = frozenset(RESULT_MATRIX_FIELDS) | {"seed_key"}
TEXT_COLUMNS = ("system", "estimator", "bounds_method", "sls_status", "notes")
INT_FIELDS = ("N", "N0", "rep")
_NOT_FLOAT = frozenset(BOOL_FIELDS + INT_FIELDS)
# every column but the surrogate id, in table order
COLUMNS = tuple(c.name for c in Result.__table__.columns if c.name != "id")


def gamma_key(gamma) -> float:
    """The gamma part of the cell key: the value, or -1 for OLS (no gamma)."""
    return OLS_GAMMA_KEY if gamma is None else float(gamma)


def row_to_record(row) -> dict:
    """A ``results`` row (ORM object or mapping) -> a section 10 record."""
    get = row.__getitem__ if hasattr(row, "keys") else (lambda k: getattr(row, k))
    out = {}
    for f in RECORD_FIELDS:
        v = get(f)
        if isinstance(v, float) and not math.isfinite(v):
            v = None
        out[f] = v
    return out


# -- one record at a time --------------------------------------------------------------
def _clean_scalar(f: str, v):
    if v is None:
        return None
    if type(v) is float and f not in _NOT_FLOAT:  # the common case: plain Python already
        return v if math.isfinite(v) else None
    v = json_value(v)
    if v is None:
        return None
    if f in BOOL_FIELDS:
        return bool(v)
    if f in INT_FIELDS:
        return int(v)
    v = float(v)
    return v if math.isfinite(v) else None


def _clean_matrix(v):
    """Nested lists of finite floats pass as they are; anything else is sanitised."""
    if type(v) is list:
        for row in v:
            if type(row) is not list:
                break
            for x in row:
                if type(x) is not float or not math.isfinite(x):
                    if x is not None:
                        break
            else:
                continue
            break
        else:
            return v
    return json_value(v)


def record_to_row(job_id: int, record: dict) -> dict:
    """A section 10 record -> a ``results`` row (NaN/inf -> NULL, numpy -> Python)."""
    row = {"job_id": job_id}
    get = record.get
    for f in RESULT_SCALAR_FIELDS:
        v = get(f)
        t = type(v)
        plain = v is None or (t is bool and f in BOOL_FIELDS) or (t is int and f in INT_FIELDS)
        row[f] = v if plain else _clean_scalar(f, v)
    for f in RESULT_MATRIX_FIELDS:
        row[f] = _clean_matrix(get(f))
    row["system"] = str(record["system"])
    row["estimator"] = str(record["estimator"])
    row["gamma_key"] = gamma_key(row["gamma"])
    row["seed_key"] = json_value(record.get("seed_key"))
    row["bounds_method"] = record.get("bounds_method")
    row["sls_status"] = record.get("sls_status")
    notes = record.get("notes")
    row["notes"] = "; ".join(notes) if isinstance(notes, (list, tuple)) else notes
    return row


def _row_tuple(row: dict) -> tuple:
    return tuple(json.dumps(row[c]) if c in JSON_COLUMNS else row[c] for c in COLUMNS)


# -- a whole unit from its columns ----------------------------------------------------
def _clean_column(f: str, col: list) -> list:
    """A record column with the values ``_clean_scalar`` would give, checked per column
    (C-speed) and cleaned value by value only when the check fails."""
    types = set(map(type, col))
    if f in BOOL_FIELDS:
        ok = types <= {bool, type(None)}
    elif f in INT_FIELDS:
        ok = types <= {int}
    elif types <= {float, type(None)}:
        a = np.array(col, dtype=float)  # None -> nan
        ok = not np.isinf(a).any() and int(np.isnan(a).sum()) == col.count(None)
    else:
        ok = False
    return col if ok else [_clean_scalar(f, v) for v in col]


def _unit_tuples(job_id: int, result: UnitResult) -> list[tuple]:
    cols = result.value_columns(as_json=JSON_COLUMNS)
    n = len(cols["system"])
    out: dict[str, list] = {"job_id": [job_id] * n}
    for f in RESULT_SCALAR_FIELDS:
        out[f] = _clean_column(f, cols[f])
    for f in TEXT_COLUMNS:
        out[f] = [None if v is None else str(v) for v in cols[f]]
    for f in JSON_COLUMNS:
        out[f] = cols[f]
    out["gamma_key"] = [gamma_key(g) for g in out["gamma"]]
    return list(zip(*(out[c] for c in COLUMNS)))


# -- the statement --------------------------------------------------------------------
def _on_conflict(quote) -> str:
    updates = ", ".join(
        f"{quote(c)} = excluded.{quote(c)}" for c in COLUMNS if c not in KEY_COLUMNS
    )
    return f"ON CONFLICT ({', '.join(quote(c) for c in KEY_COLUMNS)}) DO UPDATE SET {updates}"


@functools.lru_cache(maxsize=8)
def _upsert_sql(dialect: Dialect) -> str:
    """``INSERT .. ON CONFLICT (cell key) DO UPDATE`` with positional parameters, for
    one ``executemany``: SQLite, and PostgreSQL through a driver other than psycopg 3
    (with psycopg, COPY is used: faster than a pipelined executemany, which itself
    measured 2-5x faster than multi-row VALUES of 50-500 rows); JSON columns take
    their text (cast to json on PostgreSQL)."""
    quote = dialect.identifier_preparer.quote
    if dialect.name == "postgresql":
        marks = ["CAST(%s AS JSON)" if c in JSON_COLUMNS else "%s" for c in COLUMNS]
    elif dialect.name == "sqlite":
        marks = ["?"] * len(COLUMNS)
    else:  # pragma: no cover - the service runs on SQLite or PostgreSQL
        raise NotImplementedError(f"results upsert on {dialect.name}")
    return (
        f"INSERT INTO {quote(Result.__tablename__)} ({', '.join(map(quote, COLUMNS))}) "
        f"VALUES ({', '.join(marks)}) {_on_conflict(quote)}"
    )


def upsert_results(
    session: Session, job_id: int, records: Sequence[dict] | UnitResult
) -> dict[str, tuple]:
    """Store records (dicts, or a unit's :class:`UnitResult`) of one job; a cell
    already stored is overwritten. The records must hold each cell once (a unit's
    do; on PostgreSQL a repeated cell is an error). Returns the stored values as
    columns ({column: values}, JSON columns as text)."""
    if isinstance(records, UnitResult):
        rows = _unit_tuples(job_id, records)
    else:
        rows = [_row_tuple(record_to_row(job_id, r)) for r in records]
    if not rows:
        return {c: () for c in COLUMNS}
    conn = session.connection()
    if conn.dialect.name == "postgresql" and conn.dialect.driver == "psycopg":
        _copy_upsert(conn.connection.driver_connection, conn.dialect, rows)
    else:
        conn.exec_driver_sql(_upsert_sql(conn.dialect), rows)
    return dict(zip(COLUMNS, zip(*rows)))


STAGE = "results_stage"


@functools.lru_cache(maxsize=8)
def _stage_sql(dialect: Dialect) -> tuple[str, str, str]:
    """(create the session's staging table, COPY into it, upsert from it)."""
    quote = dialect.identifier_preparer.quote
    cols = ", ".join(quote(c) for c in COLUMNS)
    table = quote(Result.__tablename__)
    create = (
        f"CREATE TEMP TABLE IF NOT EXISTS {STAGE} ON COMMIT DELETE ROWS AS "
        f"SELECT {cols} FROM {table} WITH NO DATA"
    )
    copy = f"COPY {STAGE} ({cols}) FROM STDIN"
    upsert = f"INSERT INTO {table} ({cols}) SELECT {cols} FROM {STAGE} {_on_conflict(quote)}"
    return create, copy, upsert


def _copy_upsert(pg, dialect: Dialect, rows: list[tuple]) -> None:
    """PostgreSQL: COPY the rows into a per-connection temporary table (emptied at
    COMMIT), then one INSERT .. SELECT .. ON CONFLICT DO UPDATE. ~3x less client
    time than a pipelined executemany of 1,800 rows (measured: 100 vs 160-200 ms)."""
    create, copy, upsert = _stage_sql(dialect)
    with pg.cursor() as cur:
        cur.execute(create)
        cur.execute(f"TRUNCATE {STAGE}")  # a unit upserted twice in one transaction
        with cur.copy(copy) as cp:
            for row in rows:
                cp.write_row(row)
        cur.execute(upsert)
