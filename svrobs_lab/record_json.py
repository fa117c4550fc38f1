"""Stored results rows -> records as JSON bytes (docs/spec.md#record-fields).

The hot read path of the API (a results page, a JSONL stream). Rows come from
``results_store.record_select`` and are decoded a batch at a time by
``results_store.decode_rows`` (matrices from their float64 bytes); the records
are encoded by ``pydantic_core.to_json`` (Rust; the library FastAPI already
serialises with). Field order is the record's (``RECORD_FIELDS``); non-finite
floats become ``null``; U+0085, U+2028 and U+2029 are escaped (:data:`_LINE_SEPARATORS`).
"""

from __future__ import annotations

from collections.abc import Sequence

from pydantic_core import to_json

from service.db.result_codec import ResultCodec
from service.db.results_store import decode_rows

# Characters that JSON lets a string hold as they are but that str.splitlines() (and
# httpx's iter_lines, which the client reads JSON lines with) takes for line ends:
# written as \u escapes, a JSON line is one line to every reader (a system name may
# hold them). In UTF-8 these bytes are only ever these characters.
_LINE_SEPARATORS = (
    ("\x85".encode(), b"\\u0085"),
    ("\u2028".encode(), b"\\u2028"),
    ("\u2029".encode(), b"\\u2029"),
)


def _json(value) -> bytes:
    out = to_json(value, inf_nan_mode="null")
    if not out.isascii():  # the usual body is ASCII: one fast pass
        for raw, escaped in _LINE_SEPARATORS:
            out = out.replace(raw, escaped)
    return out


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
