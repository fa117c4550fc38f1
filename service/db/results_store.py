"""Records (docs/spec.md#record-fields) <-> ``results`` rows: one upsert on the
cell key, from record dicts or straight from a unit's column arrays; and stored
rows back to records (:func:`record_select`, :func:`decode_rows`).

The hot write path of the worker (docs/performance.md#the-store-of-a-unit). A
unit's rows are built from its column arrays (:func:`unit_columns`, no database
access: done before the write transaction) as columns in the compact format of
:mod:`service.db.result_codec` (matrices as float64 bytes, ``notes`` as an id
into ``result_notes``, ``seed_key`` NULL when derived), with no per-row
SQLAlchemy parameter processing and without the columns NULL in every row: on
SQLite one DBAPI ``executemany`` of an ``INSERT`` (of the upsert ``.. ON CONFLICT
(cell key) DO UPDATE`` for a unit stored before), its values of the types pysqlite
binds without adapting them; on PostgreSQL a binary COPY into ``results`` (or,
for a unit stored before, into a temporary table and one ``INSERT .. SELECT .. ON
CONFLICT``). Values are cleaned as the ORM would store them: NaN/inf -> NULL,
numpy scalars -> Python.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Any

from sqlalchemy import Insert, Select, Table, select
from sqlalchemy.orm import Session

from svrobs_core.parsing import parse_spec
from svrobs_core.records import BOOL_FIELDS, MATRIX_FIELDS, RECORD_FIELDS, json_value
from svrobs_core.unit_result import UnitResult

from .datasets import dataset_shape
from .models import (
    OLS_GAMMA_KEY,
    RESULT_SCALAR_FIELDS,
    Job,
    Result,
    ResultConstant,
    ResultNote,
)
from .result_codec import RADIUS_SCALAR, SHARED, SHARED_FIELDS, ResultCodec
from .results_sql import COLUMNS, KEY_COLUMNS, copy_upsert, executemany_upsert, upsert_sql

TEXT_COLUMNS = ("system", "estimator", "bounds_method", "sls_status")
INT_FIELDS = ("N", "N0", "rep")
_NOT_FLOAT = frozenset(BOOL_FIELDS + INT_FIELDS)
NOTES = ResultNote.__table__
CONSTANTS = ResultConstant.__table__


def gamma_key(gamma) -> float:
    """The gamma part of the cell key: the value, or -1 for OLS (no gamma)."""
    return OLS_GAMMA_KEY if gamma is None else float(gamma)


def job_codec(session: Session, job_id: int, spec: dict | None = None) -> ResultCodec:
    """The codec of a job's rows: from its spec (read if not given) and its constants."""
    if spec is None:
        spec = session.scalar(select(Job.spec).where(Job.id == job_id))
        assert spec is not None, f"no job {job_id}"  # the caller's job exists
    c = CONSTANTS.c
    rows = session.execute(
        select(c.system, c.sigma_w, c.field, c.value).where(c.job_id == job_id)
    ).all()
    constants = {(s, float(w), f): bytes(v) for s, w, f, v in rows}
    data = None
    if "dataset" in spec:  # its shapes follow from the dataset's n and m
        shape = dataset_shape(session, spec["dataset"])
        if shape is None:
            raise ValueError(f"job {job_id}: its dataset {spec['dataset']} is not stored")
        data = (shape.n, shape.m)
    return replace(ResultCodec.of(spec, data), constants=constants)


def _shared(session: Session, codec: ResultCodec, job_id: int, key: tuple, value: bytes) -> bool:
    """Whether ``value`` is (now) the stored constant of ``key`` = (system, sigma_w,
    field): stored if the job has none yet (a concurrent writer's wins)."""
    if key not in codec.constants:
        system, sigma_w, field = key
        row = {"job_id": job_id, "system": system, "sigma_w": sigma_w, "field": field}
        session.execute(insert_ignore(session, CONSTANTS, list(row)), [{**row, "value": value}])
        stored = session.scalar(
            select(CONSTANTS.c.value).where(*(CONSTANTS.c[k] == v for k, v in row.items()))
        )
        assert stored is not None  # inserted above, or a concurrent writer's
        codec.constants[key] = bytes(stored)
    return codec.constants[key] == value


def insert_ignore(session: Session, table: Table, key: list[str]) -> Insert:
    """``INSERT .. ON CONFLICT (key) DO NOTHING`` of ``table`` in the session's dialect."""
    if session.get_bind().dialect.name == "postgresql":
        from sqlalchemy.dialects.postgresql import insert as pg_insert

        return pg_insert(table).on_conflict_do_nothing(index_elements=key)
    from sqlalchemy.dialects.sqlite import insert as sqlite_insert

    return sqlite_insert(table).on_conflict_do_nothing(index_elements=key)


# -- notes: a dictionary of distinct texts -----------------------------------------------
def _digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def note_ids(session: Session, texts: Iterable[str | None]) -> dict[str | None, int | None]:
    """{text: its ``result_notes`` id}, adding the texts not stored yet (in digest
    order, so that concurrent writers wait on each other without a deadlock)."""
    wanted = {_digest(t): t for t in set(texts) if t is not None}
    out: dict[str | None, int | None] = {None: None}
    if not wanted:
        return out
    q = select(NOTES.c.digest, NOTES.c.id).where(NOTES.c.digest.in_(sorted(wanted)))
    found = dict(session.execute(q).all())
    missing = sorted(set(wanted) - set(found))
    if missing:
        session.execute(
            insert_ignore(session, NOTES, ["digest"]),
            [{"digest": d, "text": wanted[d]} for d in missing],
        )
        found.update(session.execute(q).all())
    out.update((wanted[d], i) for d, i in found.items())
    return out


# -- reading ---------------------------------------------------------------------------
def record_select() -> Select:
    """The select of records, columns in ``RECORD_FIELDS`` order as stored (matrices as
    bytes, ``seed_key`` as text or NULL, ``notes`` the text): decode with
    :func:`decode_rows`; add WHERE / ORDER BY."""
    t = Result.__table__
    cols = [NOTES.c.text.label("notes") if f == "notes" else t.c[f] for f in RECORD_FIELDS]
    return select(*cols).select_from(t.outerjoin(NOTES, t.c.notes_id == NOTES.c.id))


_IDX = {f: i for i, f in enumerate(RECORD_FIELDS)}


def decode_rows(rows: Sequence[Sequence], codec: ResultCodec) -> list[dict]:
    """Rows of :func:`record_select` -> records (a batch at a time)."""
    if not rows:
        return []
    cols: list[Sequence[Any]] = list(zip(*rows))
    system, sigma = cols[_IDX["system"]], cols[_IDX["sigma_w"]]
    for f in MATRIX_FIELDS:
        scalars = cols[_IDX[RADIUS_SCALAR[f]]] if f in RADIUS_SCALAR else None
        cols[_IDX[f]] = codec.decode_matrices(system, sigma, f, cols[_IDX[f]], scalars)
    cols[_IDX["seed_key"]] = codec.decode_seed_keys(
        system, *(cols[_IDX[f]] for f in ("sigma_w", "N", "rep", "seed_key"))
    )
    return [dict(zip(RECORD_FIELDS, vals)) for vals in zip(*cols)]


def load_records(session: Session, job_id: int, *conds, ordered: bool = True) -> list[dict]:
    """The job's stored records (optionally filtered), in grid order."""
    t = Result.__table__
    q = record_select().where(t.c.job_id == job_id, *conds)
    if ordered:
        q = q.order_by(*(t.c[c] for c in KEY_COLUMNS[1:]))
    return decode_rows(session.execute(q).all(), job_codec(session, job_id))


def count_cells(spec: dict, system, sigma_w, N, estimator, gamma_key, rep) -> int:
    """How many cells of the job's grid (docs/spec.md#grid-size) match the filters (each a list
    of values, or None for all): the row count of a selection of a job whose every
    cell is stored (a succeeded job), without counting rows."""
    s = parse_spec(spec)
    axis = [(e, OLS_GAMMA_KEY) for e in s.estimators if e == "ols"]
    axis += [(e, float(g)) for e in s.estimators if e != "ols" for g in s.gamma]

    def n(values, allowed) -> int:
        return len(values) if allowed is None else len(set(values) & set(allowed))

    est, gk = set(estimator or ()), set(gamma_key or ())
    n_axis = sum(1 for e, g in axis if (not est or e in est) and (not gk or g in gk))
    return (
        n(s.grid_systems, system or None)
        * n(s.grid_sigma_w, sigma_w or None)
        * n(s.N, N or None)
        * n_axis
        * (s.reps if not rep else len({r for r in rep if 0 <= r < s.reps}))
    )


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
    """A record -> a ``results`` row (NaN/inf -> NULL, numpy -> Python)."""
    row: dict[str, Any] = {"job_id": job_id}
    get = record.get
    for f in RESULT_SCALAR_FIELDS:
        v = get(f)
        t = type(v)
        plain = v is None or (t is bool and f in BOOL_FIELDS) or (t is int and f in INT_FIELDS)
        row[f] = v if plain else _clean_scalar(f, v)
    for f in MATRIX_FIELDS:
        row[f] = _clean_matrix(get(f))
    row["system"] = str(record["system"])
    row["estimator"] = str(record["estimator"])
    row["gamma_key"] = gamma_key(row["gamma"])
    row["seed_key"] = json_value(record.get("seed_key"))
    for f in ("bounds_method", "sls_status"):  # text columns: text, as SQLite would store it
        v = record.get(f)
        row[f] = None if v is None else str(v)
    notes = record.get("notes")
    notes = "; ".join(map(str, notes)) if isinstance(notes, (list, tuple)) else notes
    row["notes"] = None if notes is None else str(notes)
    return row


def _row_tuple(row: dict, codec: ResultCodec, notes: dict) -> tuple:
    """A :func:`record_to_row` dict -> the stored tuple (compact format)."""
    system = row["system"]
    out = dict(row)
    for f in MATRIX_FIELDS:
        scalar = row[RADIUS_SCALAR[f]] if f in RADIUS_SCALAR else None
        out[f] = codec.encode_matrix(system, f, row[f], scalar)
    out["seed_key"] = codec.encode_seed_key(
        system, row["sigma_w"], row["N"], row["rep"], row["seed_key"]
    )
    out["notes_id"] = notes[row["notes"]]
    return tuple(out[c] for c in COLUMNS)


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
        # every float finite: their sum is (a NaN or an infinity makes it NaN or
        # infinite; a sum that overflows only sends the column the slow way)
        ok = math.isfinite(sum(filter(None, col)))  # filter drops None (and zeros)
    else:
        ok = False
    return col if ok else [_clean_scalar(f, v) for v in col]


def _is_plain(f: str, kind: str | None) -> bool:
    """Whether a column of ``kind`` (:meth:`UnitResult.plain_fields`) holds what
    ``_clean_scalar`` gives for field ``f`` already: no value needs a check."""
    if kind == "none":
        return True
    if kind == "bool":
        return f in BOOL_FIELDS
    return kind == "float" and f not in _NOT_FLOAT


@dataclass
class UnitColumns:
    """A unit's rows as columns ({column: values}, table order), computed from its
    :class:`UnitResult` alone (:func:`unit_columns`): what storing it costs in CPU,
    done before the write transaction. ``notes_id`` holds the notes' texts, the
    shared matrices (``SHARED_FIELDS``) their blobs, and ``seed_key`` is not set
    until the job's dictionary, constants and spec are read (:func:`_finish`)."""

    result: UnitResult
    columns: dict[str, list]
    # per shared field, its (start, stop) row ranges whose blobs are all the same
    uniform: dict[str, list[tuple[int, int]]]

    @property
    def whole_groups(self) -> bool | None:
        """Whether the unit holds every repetition of its groups (None: unknown)."""
        n = self.result.n_reps
        return None if n is None else self.result.reps == list(range(n))


def unit_columns(result: UnitResult) -> UnitColumns:
    """The pure part of storing a unit (no database access)."""
    cols = result.value_columns(omit=frozenset(MATRIX_FIELDS) | {"seed_key"})
    n = len(cols["system"])
    out: dict[str, list] = {"job_id": [None] * n}
    plain = result.plain_fields()
    for f in RESULT_SCALAR_FIELDS:
        out[f] = cols[f] if _is_plain(f, plain.get(f)) else _clean_column(f, cols[f])
    for f in TEXT_COLUMNS:
        col = cols[f]
        out[f] = (
            col
            if set(map(type, col)) <= {str, type(None)}
            else [None if v is None else str(v) for v in col]
        )
    out["gamma_key"] = [gamma_key(g) for g in out["gamma"]]
    out["notes_id"] = cols["notes"]
    out["seed_key"] = [None] * n
    uniform: dict[str, list[tuple[int, int]]] = {f: [] for f in SHARED_FIELDS}
    for f in MATRIX_FIELDS:
        out[f] = []
    start = 0
    k = len(result.reps) * len(result.axis.names)
    for block in result.matrix_blocks():
        for f in MATRIX_FIELDS:
            b = block[f]
            scalars = out[RADIUS_SCALAR[f]][start : start + k] if f in RADIUS_SCALAR else None
            blobs = [None] * k if b is None else ResultCodec.encode_block(b, scalars)
            if f in SHARED_FIELDS and b is not None and len(set(blobs)) == 1:
                uniform[f].append((start, start + k))
            out[f] += blobs
        start += k
    return UnitColumns(result, {c: out[c] for c in COLUMNS}, uniform)


def _finish(job_id: int, unit: UnitColumns, codec: ResultCodec, session: Session) -> dict:
    """:func:`unit_columns` completed with what the database holds: the notes' ids,
    the job's shared matrices (stored once: the rows' blobs become ``SHARED``) and
    the seed keys the spec does not give."""
    result, out = unit.result, dict(unit.columns)
    n = len(out["system"])
    out["job_id"] = [job_id] * n
    notes = note_ids(session, out["notes_id"])
    out["notes_id"] = [notes[t] for t in out["notes_id"]]
    sigma_w = float(result.sigma_w)
    for f, ranges in unit.uniform.items():
        col = out[f] = list(out[f])
        for start, stop in ranges:
            if _shared(session, codec, job_id, (result.system, sigma_w, f), col[start]):
                col[start:stop] = [SHARED] * (stop - start)
    derived = (
        codec.system_index.get(result.system) == result.system_idx
        and codec.sigma_index.get(float(result.sigma_w)) == result.sigma_w_idx
    )
    if not derived:  # else the spec gives every seed_key: stored as NULL
        keys = result.value_columns(omit=frozenset(RECORD_FIELDS) - {"seed_key"})["seed_key"]
        out["seed_key"] = [
            codec.encode_seed_key(result.system, result.sigma_w, N, r, v)
            for N, r, v in zip(out["N"], out["rep"], keys)
        ]
    return out


def upsert_results(
    session: Session, job_id: int, records: Sequence[dict] | UnitResult | UnitColumns
) -> dict[str, Sequence]:
    """Store records (dicts, or a unit's :class:`UnitResult` or its
    :func:`unit_columns`) of one job; a cell
    already stored is overwritten. The records must hold each cell once (a unit's
    do; on PostgreSQL a repeated cell is an error). Returns the stored values as
    columns ({column: values}, in the stored format)."""
    codec = job_codec(session, job_id)
    if isinstance(records, UnitResult):
        records = unit_columns(records)
    if isinstance(records, UnitColumns):
        columns: dict[str, Sequence] = _finish(job_id, records, codec, session)
    else:
        dicts = [record_to_row(job_id, r) for r in records]
        notes = note_ids(session, (d["notes"] for d in dicts))
        rows = [_row_tuple(d, codec, notes) for d in dicts]
        columns = dict(zip(COLUMNS, zip(*rows))) if rows else {c: () for c in COLUMNS}
    if not columns["job_id"]:
        return {c: () for c in COLUMNS}
    conn = session.connection()
    if conn.dialect.name == "postgresql" and conn.dialect.driver == "psycopg":
        copy_upsert(conn.connection.driver_connection, conn.dialect, columns)
    elif conn.dialect.name == "sqlite":
        executemany_upsert(conn, columns)
    else:
        conn.exec_driver_sql(upsert_sql(conn.dialect), list(zip(*columns.values())))
    return columns
