"""Stored results rows -> records as JSON bytes (docs/spec.md#record-fields).

The hot read path of the API (a results page, a JSONL stream). Rows come from
``results_store.record_select`` and are decoded a batch at a time by
``results_store.decode_rows`` (matrices from their float64 bytes); the records
are encoded by ``pydantic_core.to_json`` (Rust; the library FastAPI already
serialises with). Field order is the record's (``RECORD_FIELDS``); non-finite
floats become ``null``.
"""

from __future__ import annotations

from collections.abc import Sequence

from pydantic_core import to_json

from service.db.result_codec import ResultCodec
from service.db.results_store import decode_rows


def _json(value) -> bytes:
    return to_json(value, inf_nan_mode="null")


def encode_page(
    rows: Sequence[Sequence],
    codec: ResultCodec,
    total: int,
    limit: int,
    offset: int,
    *,
    next_offset: int | None = None,
) -> bytes:
    """A ``ResultPage`` body: ``{"items": [...], "total", "limit", "offset",
    "next_offset"}``."""
    items = decode_rows(rows, codec)
    page = {"items": items, "total": total, "limit": limit, "offset": offset}
    return _json(page | {"next_offset": next_offset})


def encode_lines(rows: Sequence[Sequence], codec: ResultCodec) -> bytes:
    """JSON lines, one record each."""
    return b"".join(_json(rec) + b"\n" for rec in decode_rows(rows, codec))
