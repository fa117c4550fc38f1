"""The SQL of the results write (:func:`service.db.results_store.upsert_results`):
a unit's rows as columns ({column: values}, table order, stored format) ->
SQLite's ``executemany`` or PostgreSQL's binary COPY
(docs/performance.md#the-store-of-a-unit)."""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence

from sqlalchemy import Boolean, Float, Integer, LargeBinary
from sqlalchemy.engine import Dialect
from sqlalchemy.exc import IntegrityError

from svrobs_core.records import BOOL_FIELDS, MATRIX_FIELDS

from .models import RESULT_KEY, Result

KEY_COLUMNS = RESULT_KEY
COLUMNS = tuple(c.name for c in Result.__table__.columns)  # in table order


# -- the statement --------------------------------------------------------------------
def _on_conflict(quote) -> str:
    updates = ", ".join(
        f"{quote(c)} = excluded.{quote(c)}" for c in COLUMNS if c not in KEY_COLUMNS
    )
    return f"ON CONFLICT ({', '.join(quote(c) for c in KEY_COLUMNS)}) DO UPDATE SET {updates}"


@functools.lru_cache(maxsize=64)
def _insert_sql(dialect: Dialect, columns: tuple[str, ...] = COLUMNS) -> str:
    """``INSERT`` of ``columns`` (the others take their default, NULL) with positional
    parameters, for one ``executemany``."""
    quote = dialect.identifier_preparer.quote
    if dialect.name == "postgresql":
        marks = ["%s"] * len(columns)
    elif dialect.name == "sqlite":
        marks = ["?"] * len(columns)
    else:  # pragma: no cover - the service runs on SQLite or PostgreSQL
        raise NotImplementedError(f"results upsert on {dialect.name}")
    return (
        f"INSERT INTO {quote(Result.__tablename__)} ({', '.join(map(quote, columns))}) "
        f"VALUES ({', '.join(marks)})"
    )


@functools.lru_cache(maxsize=64)
def upsert_sql(dialect: Dialect, columns: tuple[str, ...] = COLUMNS) -> str:
    """:func:`_insert_sql` ``ON CONFLICT (cell key) DO UPDATE`` (a column not sent is
    updated to NULL too: ``excluded`` holds the defaults): SQLite, and PostgreSQL
    through a driver other than psycopg 3 (with psycopg, COPY is used: faster than a
    pipelined executemany, which itself measured 2-5x faster than multi-row VALUES of
    50-500 rows)."""
    return f"{_insert_sql(dialect, columns)} {_on_conflict(dialect.identifier_preparer.quote)}"


_KEY = frozenset(KEY_COLUMNS)
_BLOB_COLUMNS = frozenset(MATRIX_FIELDS)
_BOOL_COLUMNS = frozenset(BOOL_FIELDS)
_BOOL_INT = {True: 1, False: 0, None: None}


def _bound_columns(columns: dict[str, Sequence]) -> tuple[str, ...]:
    """The columns to send: the key and every column with a value in some row (a
    column that is NULL in every row is left to its default, NULL)."""
    return tuple(c for c in COLUMNS if c in _KEY or _has_value(columns[c]))


def _has_value(col: Sequence) -> bool:
    """Whether some value of ``col`` is not None (the first one, mostly; else a count
    at C speed)."""
    return len(col) > 0 and (col[0] is not None or col.count(None) != len(col))


def _sqlite_column(c: str, values: Sequence) -> Sequence:
    """Values of one column as pysqlite binds them without its adaptation protocol
    (which it tries, raising and catching two AttributeErrors, for every value that is
    not exactly int, float, str or bytearray: None, bool, bytes). The stored values
    are the same: a bool is stored as the integer 0/1 either way, a bytearray as the
    blob of its bytes; the NULLs of a column are left to its default where possible."""
    if c in _BOOL_COLUMNS:
        return [_BOOL_INT[v] for v in values]
    if c in _BLOB_COLUMNS:
        return [None if v is None else bytearray(v) for v in values]
    return values


def executemany_upsert(conn, columns: dict[str, Sequence]) -> None:
    """SQLite: one ``executemany`` of a plain INSERT (a unit's first store: no cell of
    it is there yet; ~20 % less time than the upsert), and when a cell is there (a
    redelivered unit), back to the savepoint and one of the upsert."""
    used = _bound_columns(columns)
    rows = list(zip(*(_sqlite_column(c, columns[c]) for c in used)))
    conn.exec_driver_sql("SAVEPOINT results_insert")
    try:
        conn.exec_driver_sql(_insert_sql(conn.dialect, used), rows)
    except IntegrityError:
        conn.exec_driver_sql("ROLLBACK TO SAVEPOINT results_insert")
        conn.exec_driver_sql("RELEASE SAVEPOINT results_insert")
        conn.exec_driver_sql(upsert_sql(conn.dialect, used), rows)
    else:
        conn.exec_driver_sql("RELEASE SAVEPOINT results_insert")


STAGE = "results_stage"


@functools.lru_cache(maxsize=64)
def _copy_sql(dialect: Dialect, columns: tuple[str, ...] = COLUMNS) -> dict[str, str]:
    """COPY of ``columns`` straight into ``results``; else the session's staging table
    (create, COPY into it, upsert from it: every column, the others NULL)."""
    quote = dialect.identifier_preparer.quote
    every = ", ".join(quote(c) for c in COLUMNS)
    cols = ", ".join(quote(c) for c in columns)
    table = quote(Result.__tablename__)
    return {
        "direct": f"COPY {table} ({cols}) FROM STDIN (FORMAT BINARY)",
        "create": (
            f"CREATE TEMP TABLE IF NOT EXISTS {STAGE} ON COMMIT DELETE ROWS AS "
            f"SELECT {every} FROM {table} WITH NO DATA"
        ),
        "stage": f"COPY {STAGE} ({cols}) FROM STDIN (FORMAT BINARY)",
        "upsert": (
            f"INSERT INTO {table} ({every}) SELECT {every} FROM {STAGE} {_on_conflict(quote)}"
        ),
    }


def _pg_type(column) -> str:
    t = column.type
    for py, name in ((Boolean, "bool"), (Integer, "int4"), (Float, "float8")):
        if isinstance(t, py):
            return name
    return "bytea" if isinstance(t, LargeBinary) else "text"


PG_TYPES = {c.name: _pg_type(c) for c in Result.__table__.columns}


def _copy(cur, sql: str, types: list[str], rows: Iterable[tuple]) -> None:
    """Binary COPY (the values dumped by type: ~4x less time than the text format)."""
    with cur.copy(sql) as cp:
        cp.set_types(types)
        for row in rows:
            cp.write_row(row)


def copy_upsert(pg, dialect: Dialect, columns: dict[str, Sequence]) -> None:
    """PostgreSQL: COPY the rows straight into ``results`` (a unit's first store: no
    cell of it is there yet); when a cell is (a redelivered unit: unique violation),
    back to the savepoint, COPY into a per-connection temporary table (emptied at
    COMMIT) and one INSERT .. SELECT .. ON CONFLICT DO UPDATE. The direct COPY costs
    the server about half of the staged upsert. Columns NULL in every row are not
    sent (their default is NULL)."""
    import psycopg

    used = _bound_columns(columns)
    sql = _copy_sql(dialect, used)
    types = [PG_TYPES[c] for c in used]
    rows = list(zip(*(columns[c] for c in used)))
    with pg.cursor() as cur:
        cur.execute("SAVEPOINT results_copy")
        try:
            _copy(cur, sql["direct"], types, rows)
        except psycopg.errors.UniqueViolation:
            cur.execute("ROLLBACK TO SAVEPOINT results_copy")
        else:
            cur.execute("RELEASE SAVEPOINT results_copy")
            return
        cur.execute(sql["create"])
        cur.execute(f"TRUNCATE {STAGE}")  # a unit upserted twice in one transaction
        _copy(cur, sql["stage"], types, rows)
        cur.execute(sql["upsert"])
