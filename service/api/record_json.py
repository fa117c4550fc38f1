"""Stored results rows -> section 10 records as JSON bytes (SPEC section 10).

The hot read path of the API (a results page, a JSONL stream). Matrix and
``seed_key`` columns are selected as their stored JSON text (``CAST .. AS
TEXT`` on every dialect, so neither the driver nor SQLAlchemy decodes them
one by one), decoded for a whole batch in one ``pydantic_core.from_json``
call, and the records are encoded by ``pydantic_core.to_json`` (Rust; the
library FastAPI already serialises with). Field order is the record's
(``RECORD_FIELDS``); non-finite floats become ``null``. The parsed value equals
``results_store.row_to_record`` of the same row (tested).
"""

from __future__ import annotations

from collections.abc import Sequence

from pydantic_core import from_json, to_json
from sqlalchemy import Text, cast

from service.db.models import Result
from svrobs_core.records import MATRIX_FIELDS, RECORD_FIELDS

# a record's stored columns as SQLAlchemy decodes them, and the order results are listed in
RESULT_COLUMNS = [Result.__table__.c[f] for f in RECORD_FIELDS]
ORDER = [Result.__table__.c[f] for f in ("system", "sigma_w", "N", "estimator", "gamma_key", "rep")]

RAW_JSON_FIELDS = frozenset(MATRIX_FIELDS) | {"seed_key"}
_RAW_IDX = tuple(i for i, f in enumerate(RECORD_FIELDS) if f in RAW_JSON_FIELDS)
_RAW_NAMES = tuple(RECORD_FIELDS[i] for i in _RAW_IDX)


def record_columns() -> list:
    """The select list of a record: JSON columns as text, the rest as stored."""
    t = Result.__table__
    return [cast(t.c[f], Text).label(f) if f in RAW_JSON_FIELDS else t.c[f] for f in RECORD_FIELDS]


def decode_rows(rows: Sequence[Sequence]) -> list[dict]:
    """Rows in :func:`record_columns` order -> records (JSON columns decoded, all
    rows' JSON text in one parse)."""
    text = ",".join(r[i] or "null" for r in rows for i in _RAW_IDX)
    decoded = iter(from_json("[" + text + "]"))
    out = []
    for r in rows:
        rec = dict(zip(RECORD_FIELDS, r))
        for name in _RAW_NAMES:
            rec[name] = next(decoded)
        out.append(rec)
    return out


def _json(value) -> bytes:
    return to_json(value, inf_nan_mode="null")


def encode_page(rows: Sequence[Sequence], total: int, limit: int, offset: int) -> bytes:
    """A ``ResultPage`` body: ``{"items": [...], "total", "limit", "offset"}``."""
    return _json({"items": decode_rows(rows), "total": total, "limit": limit, "offset": offset})


def encode_lines(rows: Sequence[Sequence]) -> bytes:
    """JSON lines, one record each."""
    return b"".join(_json(rec) + b"\n" for rec in decode_rows(rows))
