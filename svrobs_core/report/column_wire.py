"""How :class:`~.columns.Columns` travel to another process
(docs/performance.md#figures-drawn-beside-the-build): narrowed to the fields a
figure reads (:func:`narrow`), and pickled with each field that its codes give back
exactly sent as those codes alone (:func:`pack`, :func:`unpack`)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from ..array_types import Array

# A field's cached codes: (integer codes, the value of each code).
Codes = tuple[Array, list[Any]]


class Withheld(dict[str, Array]):
    """The fields of a Columns of which others were left out (:func:`narrow`):
    looking up one of those raises KeyError, so that a figure built from too few
    fields fails rather than drawing them as fields without data."""

    def __init__(self, data: dict[str, Array], withheld: Iterable[str]) -> None:
        super().__init__(data)
        self.withheld = frozenset(withheld)

    def _check(self, f: object) -> None:
        if f in self.withheld:
            raise KeyError(f"{f} (not sent with the figure)")

    def __getitem__(self, f: str) -> Array:
        self._check(f)
        return super().__getitem__(f)

    def get(self, f: str, default: Any = None) -> Any:
        self._check(f)
        return super().get(f, default)

    def __contains__(self, f: object) -> bool:
        self._check(f)
        return super().__contains__(f)


def _codes_of(data: dict[str, Array], cache: dict[Any, Any]) -> dict[str, Codes]:
    return {f: cache[("codes", f)] for f in data if ("codes", f) in cache}


def narrow(
    data: dict[str, Array], cache: dict[Any, Any], fields: Iterable[str]
) -> tuple[Withheld, dict[str, Codes]]:
    """The columns ``fields`` of ``data`` (those present; the others withheld) and
    their cached codes."""
    keep = set(fields)
    out = Withheld(
        {f: a for f, a in data.items() if f in keep},
        [*getattr(data, "withheld", ()), *(f for f in data if f not in keep)],
    )
    return out, _codes_of(out, cache)


def pack(data: dict[str, Array], cache: dict[Any, Any], n: int) -> dict[str, Any]:
    """A Columns' picklable state: its fields and their cached codes. A field with
    codes whose values its codes give back exactly (text, or floats none of which is
    zero, whose sign the codes do not keep) travels as the codes alone, in the
    smallest integer type, and is rebuilt on arrival."""
    codes = _codes_of(data, cache)
    rebuilt = {f for f, a in data.items() if f in codes and _rebuildable(a, codes[f][1])}
    sent = {
        f: (c.astype(np.min_scalar_type(max(len(v) - 1, 0))), v, c.dtype, data[f].dtype)
        for f, (c, v) in codes.items()
    }
    return {
        "data": {f: (None if f in rebuilt else a) for f, a in data.items()},
        "n": n,
        "codes": sent,
        "withheld": sorted(getattr(data, "withheld", ())),
    }


def unpack(state: dict[str, Any]) -> tuple[dict[str, Array], dict[str, Codes], int]:
    """(fields, cached codes, row count) of a state :func:`pack` made."""
    codes = {f: (c.astype(dt), v) for f, (c, v, dt, _) in state["codes"].items()}
    data = {
        f: (_from_codes(*codes[f], state["codes"][f][3]) if a is None else a)
        for f, a in state["data"].items()
    }
    return (Withheld(data, state["withheld"]) if state["withheld"] else data), codes, state["n"]


def _rebuildable(col: Array, values: list[Any]) -> bool:
    """Whether ``_from_codes`` gives ``col`` back from its codes and ``values``."""
    if col.dtype == object:
        return all(v is None or type(v) is str for v in values)
    return col.dtype == np.float64 and col.ndim == 1 and all(v != 0.0 for v in values)


def _from_codes(codes: Array, values: list[Any], dtype: Any) -> Array:
    """The column (of ``dtype``: object, or float64 with None as NaN) whose codes and
    values these are."""
    if np.dtype(dtype).kind == "O":
        lut = np.empty(len(values), dtype=object)
        for i, v in enumerate(values):
            lut[i] = v
    else:
        lut = np.array([np.nan if v is None else v for v in values], dtype=np.float64)
    out: Array = lut[codes]
    return out
