"""The checks of many systems at once: a spec's systems resolved as
:func:`~svrobs_core.systems.resolve_system` resolves each (docs/spec.md#system-objects).

:func:`resolve_systems` reads each system object once (its keys, name and the types
of its entries: Python objects, so one pass over them), then checks the numbers of
every system of one shape together, on stacked arrays: finiteness, magnitude, the
noise levels and cond(C) where sigma_v = 0. A system it cannot take that way (a
preset name, an entry that is not a plain int or float, a shape or number the
checks refuse) is resolved by :func:`resolve_system` itself, in the spec's order,
so an invalid spec raises the very error, naming the same field, that resolving
the systems one by one raises first.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from itertools import chain
from operator import itemgetter
from typing import Any, cast

import numpy as np

from .array_types import BoolArray, FloatArray
from .systems import (
    _SYSTEM_KEYS,
    MAX_DIM,
    MAX_ENTRY,
    SIGMA_V0_COND_LIMIT,
    SystemSpec,
    resolve_system,
)
from .text import printable

_NUMBER_TYPES = frozenset((int, float))  # exact types: bool and str are refused
_ROW_TYPES = frozenset((list,))
_REQUIRED = frozenset(("name", "A", "B"))


# (n, m, p, C given, B a flat column): the systems checked together
_Key = tuple[int, int, int, bool, bool]


def _rows(value: object) -> tuple[int, int] | None:
    """(rows, columns) of a non-empty list of equal-length non-empty lists of plain
    numbers; None for anything else."""
    if type(value) is not list or not value or not set(map(type, value)) <= _ROW_TYPES:
        return None
    widths = set(map(len, value))
    cols = widths.pop()
    if widths or not cols or not set(map(type, chain.from_iterable(value))) <= _NUMBER_TYPES:
        return None
    return len(value), cols


def _plain(obj: object) -> _Key | None:
    """The key of a system object the stacked checks take, or None for one
    :func:`resolve_system` resolves alone."""
    if type(obj) is not dict or not obj.keys() <= _SYSTEM_KEYS or not _REQUIRED <= obj.keys():
        return None
    name = obj["name"]
    if type(name) is not str or len(name) > 64 or not name.strip() or not printable(name):
        return None
    if not {type(obj.get("sigma_u", 1.0)), type(obj.get("sigma_v", 0.1))} <= _NUMBER_TYPES:
        return None
    A_value, B_value, C_value = obj["A"], obj["B"], obj.get("C")
    A = _rows(A_value)
    column = type(B_value) is list and bool(B_value) and set(map(type, B_value)) <= _NUMBER_TYPES
    B = (len(B_value), 1) if column else _rows(B_value)
    if A is None or B is None:
        return None
    n = A[0]
    if A[1] != n or n > MAX_DIM or B[0] != n or B[1] > MAX_DIM:
        return None
    C = (n, n) if C_value is None else _rows(C_value)
    if C is None or C[1] != n or C[0] > MAX_DIM:
        return None
    return n, B[1], C[0], C_value is not None, column


def _stack(
    matrices: Iterable[list[Any]], shape: tuple[int, int, int], *, flat: bool = False
) -> FloatArray:
    """``shape[0]`` matrices (lists of rows, or with ``flat`` of numbers) as one float
    array, each number converted as ``np.array(matrix, dtype=float)`` converts it."""
    rows = chain.from_iterable(matrices)
    entries = list(rows if flat else chain.from_iterable(rows))
    return np.array(entries, dtype=float).reshape(shape)


def _bad_entries(arr: FloatArray) -> BoolArray:
    """Per matrix of a stack: an entry NaN, infinite or larger than MAX_ENTRY."""
    bad: BoolArray = ~np.all(np.isfinite(arr) & (np.abs(arr) <= MAX_ENTRY), axis=(-2, -1))
    return bad


def _bad_noise(values: list[Any], *, allow_zero: bool) -> tuple[FloatArray, BoolArray]:
    """The noise levels as floats and, per system, whether the check refuses one."""
    v = np.array(values, dtype=float)
    low = v < 0 if allow_zero else v <= 0
    return v, ~np.isfinite(v) | low | (v > MAX_ENTRY)


def _group(key: _Key, members: list[dict[str, Any]]) -> list[SystemSpec | None]:
    """The systems of one key, each None where a stacked check refuses it."""
    n, m, p, given_C, column = key
    k = len(members)
    try:
        A = _stack(map(itemgetter("A"), members), (k, n, n))
        B = _stack(map(itemgetter("B"), members), (k, n, m), flat=column)
        if given_C:
            C = _stack(map(itemgetter("C"), members), (k, p, n))
        else:
            C = np.broadcast_to(np.eye(n), (k, n, n)).copy()
        sigma_u, bad_u = _bad_noise([s.get("sigma_u", 1.0) for s in members], allow_zero=False)
        sigma_v, bad_v = _bad_noise([s.get("sigma_v", 0.1) for s in members], allow_zero=True)
    except (TypeError, ValueError, OverflowError):  # an int beyond float's range
        return [None] * k
    bad = _bad_entries(A) | _bad_entries(B) | _bad_entries(C) | bad_u | bad_v
    zero = (sigma_v == 0.0) & ~bad
    if zero.any():
        if p != n:
            bad |= zero
        else:
            try:
                cond = np.linalg.cond(C[zero])
            except np.linalg.LinAlgError:  # resolve_system raises it for its system
                bad |= zero
            else:
                bad[zero] = ~(cond <= SIGMA_V0_COND_LIMIT)
    for arr in (A, B, C):
        arr.setflags(write=False)
    names = map(str.strip, map(itemgetter("name"), members))
    rows = zip(names, bad.tolist(), list(A), list(B), list(C), sigma_u.tolist(), sigma_v.tolist())
    return [
        None if refused else SystemSpec(name=name, A=a, B=b, C=c, sigma_u=u, sigma_v=v)
        for name, refused, a, b, c, u, v in rows
    ]


def resolve_systems(raw: Sequence[object], field: str = "systems") -> tuple[SystemSpec, ...]:
    """``tuple(resolve_system(s, field=f"{field}[{i}]") for i, s in enumerate(raw))``, with
    the same systems and, for an invalid one, the same first :class:`SpecError`; the
    numbers of the systems of each shape checked together."""
    out: list[SystemSpec | None] = [None] * len(raw)
    alone: list[int] = []  # resolved by resolve_system, in order
    groups: dict[_Key, list[int]] = {}
    for i, obj in enumerate(raw):
        key = _plain(obj)
        if key is None:
            alone.append(i)
        else:
            groups.setdefault(key, []).append(i)
    for key, members in groups.items():
        systems = _group(key, [cast(dict[str, Any], raw[i]) for i in members])
        for i, system in zip(members, systems, strict=True):
            if system is None:
                alone.append(i)
            else:
                out[i] = system
    for i in sorted(alone):
        out[i] = resolve_system(raw[i], field=f"{field}[{i}]")
    return tuple(s for s in out if s is not None)


__all__ = ["resolve_systems"]
