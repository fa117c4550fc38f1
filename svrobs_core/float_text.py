"""JSON text of many floats at once, as ``json.dumps`` writes them
(docs/performance.md#records-as-json-text).

``json.dumps`` writes a float as ``repr(float)`` (the shortest text that reads
back to the same double) and a nested list with ", " between items.
:func:`json_texts` gives, for every row of an array, the text ``json.dumps``
writes for ``json_value(row)`` (NaN and infinities as ``null``), to the byte,
several times faster than ``map(repr, ...)``: orjson writes the whole array in
one call, with the shortest digits (the same digits as ``repr``). Its layout
differs from Python's only for 1e-9 <= |x| < 1e-4 (orjson writes ``1e-7`` and
``0.00001`` where Python writes ``1e-07`` and ``1e-05``), so those entries are
written by ``repr`` itself: they go to orjson as NaN (text ``null``) and their
``repr`` is put in the place of that ``null``.
"""

from __future__ import annotations

import numpy as np
import orjson
from numpy.typing import ArrayLike

# |x| in [LOW, HIGH): orjson's text may differ from repr (a margin below 1e-9)
_LOW, _HIGH = 1e-10, 1e-4


def _orjson_text(arr: np.ndarray) -> bytes:
    """The JSON text of ``arr`` (C-contiguous float64) in Python's layout of floats."""
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
