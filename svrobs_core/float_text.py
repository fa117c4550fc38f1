"""JSON text of many floats at once, as ``json.dumps`` writes them
(docs/performance.md#records-as-json-text).

``json.dumps`` writes a float as ``repr(float)`` (the shortest text that reads
back to the same double) and a nested list with ", " between items.
:func:`json_texts` gives, for every row of an array, the text ``json.dumps``
writes for ``json_value(row)`` (NaN and infinities as ``null``), to the byte,
several times faster than ``map(repr, ...)``: orjson writes the whole array in
one call, with the shortest digits (the same digits as ``repr``). Its layout
differs from Python's only for 1e-9 <= |x| < 1e-4 (orjson writes ``1e-7`` and
``0.00001`` where Python writes ``1e-07`` and ``1e-05``), so the entries with
1e-10 <= |x| < 1e-4 (a margin below) are written by ``repr`` itself: they go to
orjson as NaN (text ``null``) and their ``repr`` is put in the place of that
``null``. orjson before 3.11.7 wrote ``1e16`` for Python's ``1e+16``: at import
the module checks orjson's text of a few such values, and where it differs every
array is written by ``repr`` (the same text, slower).
"""

from __future__ import annotations

import math

import numpy as np
import orjson
from numpy.typing import ArrayLike

# |x| in [LOW, HIGH): orjson's text may differ from repr (a margin below 1e-9)
_LOW, _HIGH = 1e-10, 1e-4
# values whose text orjson must write as repr does for the fast path to be used
_PROBE = [1e16, -1.5e300, 1.2345678901234568e17, 5e-324, -0.0, 0.1, 1e-11, 123456.0]


def _orjson_writes_repr() -> bool:
    text = orjson.dumps(np.array(_PROBE), option=orjson.OPT_SERIALIZE_NUMPY)
    return text == ("[" + ",".join(map(repr, _PROBE)) + "]").encode()


_FAST = _orjson_writes_repr()


def _repr_text(arr: np.ndarray) -> bytes:
    """The JSON text of a float array by ``repr`` of each entry (NaN/inf as null)."""

    def write(a: np.ndarray) -> str:
        if a.ndim == 1:
            return "[" + ",".join(repr(x) if math.isfinite(x) else "null" for x in a.tolist()) + "]"
        return "[" + ",".join(write(b) for b in a) + "]"

    return write(arr).encode()


def _orjson_text(arr: np.ndarray) -> bytes:
    """The JSON text of ``arr`` (C-contiguous float64) in Python's layout of floats."""
    if not _FAST:
        return _repr_text(arr)
    mag = np.abs(arr)
    odd = (mag >= _LOW) & (mag < _HIGH)
    if not odd.any():
        return orjson.dumps(arr, option=orjson.OPT_SERIALIZE_NUMPY)
    nulls = odd | ~np.isfinite(arr)
    text = orjson.dumps(np.where(odd, np.nan, arr), option=orjson.OPT_SERIALIZE_NUMPY)
    parts = text.split(b"null")
    fill = np.full(int(nulls.sum()), b"null", dtype=object)
    fill[odd[nulls]] = [repr(x).encode() for x in arr[odd].tolist()]
    out: list[bytes] = [b""] * (2 * len(parts) - 1)
    out[0::2] = parts
    out[1::2] = fill.tolist()
    return b"".join(out)


def json_texts(values: ArrayLike) -> list[str]:
    """One JSON text per row of ``values`` (shape (k, ...), float): for a row of
    one number ``repr(x)``, for a row that is an array the nested lists
    ``json.dumps`` writes (items joined by ", "); NaN and infinities are
    ``null``. A row with no entries (shape (k, 0, ...)) is not supported."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 0:
        raise ValueError("json_texts: an array of rows is needed, not a scalar")
    if arr.shape[0] == 0:
        return []
    if arr.size == 0:
        raise ValueError("json_texts: rows without entries are not supported")
    text = _orjson_text(np.ascontiguousarray(arr))
    if arr.ndim == 1:
        return text[1:-1].decode("ascii").split(",")
    depth = arr.ndim - 1
    body = text[1:-1].replace(b",", b", ").decode("ascii")
    # rows are separated by "]...], [...[" (depth brackets each side), nowhere else
    sep = "]" * depth + ", " + "[" * depth
    return body.replace(sep, "]" * depth + "\n" + "[" * depth).split("\n")


__all__ = ["json_texts"]
