"""System specs and the paper's presets (docs/science.md#11-the-system,
docs/science.md#91-the-preset-paper-section-6)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .array_types import FloatArray
from .errors import SpecError
from .text import printable

_PAPER_B = [[1.0], [1.5], [2.0]]


def _paper_A(diag: float) -> list[list[float]]:
    return [[diag, 0.01, 0.0], [0.01, diag, 0.01], [0.0, 0.01, diag]]


PRESETS: dict[str, dict[str, Any]] = {
    "paper-stable": {"A": _paper_A(0.9), "B": _PAPER_B, "sigma_u": 1.0, "sigma_v": 0.1},
    "paper-unstable": {"A": _paper_A(1.01), "B": _PAPER_B, "sigma_u": 1.0, "sigma_v": 0.1},
}


@dataclass(frozen=True, kw_only=True)
class SystemSpec:
    """One true system: x+ = A x + B u + w, y = C x + v (docs/science.md#11-the-system)."""

    name: str
    A: FloatArray
    B: FloatArray
    C: FloatArray
    sigma_u: float = 1.0
    sigma_v: float = 0.1

    @property
    def n(self) -> int:
        return int(self.A.shape[0])

    @property
    def m(self) -> int:
        return int(self.B.shape[1])

    @property
    def p(self) -> int:
        return int(self.C.shape[0])

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "A": self.A.tolist(),
            "B": self.B.tolist(),
            "C": self.C.tolist(),
            "sigma_u": self.sigma_u,
            "sigma_v": self.sigma_v,
        }


MAX_ENTRY = 1e100  # |entries| of A, B, C and the noise levels: the square of one entry is finite
MAX_DIM = 50  # n, m, p (svrobs_core.spec.MAX_STATE_DIM)
# sigma_v = 0 needs cond(C) below this (K = A C^-1, docs/science.md#5-the-optimal-gain-k)
SIGMA_V0_COND_LIMIT = 1e12


def _numbers(value: object) -> bool:
    """True for a (nested) list of JSON numbers: no booleans, no strings like "0.5"."""
    if isinstance(value, list):
        return all(_numbers(v) for v in value)
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _matrix(value: object, field: str) -> FloatArray:
    if not isinstance(value, list) or not _numbers(value):
        raise SpecError(field, "must be a matrix of numbers (a list of rows of numbers)")
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise SpecError(field, "must be a matrix of numbers (a list of rows)") from None
    if arr.ndim == 1 and arr.size > 0 and field.endswith(".B"):
        arr = arr[:, None]  # a column vector written as a flat list
    if arr.ndim != 2 or arr.size == 0:
        raise SpecError(field, "must be a non-empty matrix (a list of equal-length rows)")
    if not np.all(np.isfinite(arr)):
        raise SpecError(field, "contains NaN or inf")
    if np.any(np.abs(arr) > MAX_ENTRY):
        raise SpecError(field, f"has an entry larger than {MAX_ENTRY:g} in magnitude")
    if max(arr.shape) > MAX_DIM:
        raise SpecError(field, f"is {arr.shape[0]}x{arr.shape[1]}: at most {MAX_DIM} per side")
    return arr


def _positive_number(value: object, field: str, *, allow_zero: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SpecError(field, "must be a number")
    try:
        v = float(value)
    except OverflowError:  # an integer beyond the double range
        v = math.inf
    if not np.isfinite(v):
        raise SpecError(field, "must be finite")
    if v < 0 or (v == 0 and not allow_zero):
        raise SpecError(field, "must be > 0" if not allow_zero else "must be >= 0")
    if v > MAX_ENTRY:
        raise SpecError(field, f"must be at most {MAX_ENTRY:g}")
    return v


_SYSTEM_KEYS = {"name", "A", "B", "C", "sigma_u", "sigma_v"}


def resolve_system(obj: object, *, field: str = "systems[0]") -> SystemSpec:
    """A preset name or a ``{name, A, B, C, sigma_u, sigma_v}`` object -> SystemSpec.

    A spec's systems are resolved by :func:`svrobs_core.system_batch.resolve_systems`,
    which checks the systems of one shape together and gives the same systems and
    errors: a check added here needs its stacked form there (the test of both is
    ``tests/core/test_system_batch.py``)."""
    if isinstance(obj, str):
        if obj not in PRESETS:
            raise SpecError(field, f"unknown preset {obj!r}; known: {sorted(PRESETS)}")
        obj = {"name": obj, **PRESETS[obj]}
    if not isinstance(obj, dict):
        raise SpecError(field, "must be a preset name or an object {name, A, B, ...}")
    unknown = set(obj) - _SYSTEM_KEYS
    if unknown:
        raise SpecError(f"{field}.{sorted(unknown)[0]}", "unknown field")
    for key in ("name", "A", "B"):
        if key not in obj:
            raise SpecError(f"{field}.{key}", "is required")
    name = obj["name"]
    if not isinstance(name, str) or not name.strip() or len(name) > 64 or not printable(name):
        raise SpecError(
            f"{field}.name",
            "must be a non-empty string of at most 64 printable characters (no control characters)",
        )
    A = _matrix(obj["A"], f"{field}.A")
    if A.shape[0] != A.shape[1]:
        raise SpecError(f"{field}.A", f"must be square, got {A.shape[0]}x{A.shape[1]}")
    n = A.shape[0]
    B = _matrix(obj["B"], f"{field}.B")
    if B.shape[0] != n:
        raise SpecError(f"{field}.B", f"must have {n} rows (as many as A), got {B.shape[0]}")
    C = np.eye(n) if obj.get("C") is None else _matrix(obj["C"], f"{field}.C")
    if C.shape[1] != n:
        raise SpecError(f"{field}.C", f"must have {n} columns (as many as A), got {C.shape[1]}")
    sigma_u = _positive_number(obj.get("sigma_u", 1.0), f"{field}.sigma_u", allow_zero=False)
    sigma_v = _positive_number(obj.get("sigma_v", 0.1), f"{field}.sigma_v", allow_zero=True)
    if sigma_v == 0.0:
        square = C.shape[0] == C.shape[1]
        if not square or not np.linalg.cond(C) <= SIGMA_V0_COND_LIMIT:
            raise SpecError(
                f"{field}.sigma_v",
                "sigma_v = 0 needs a square invertible C with cond(C) <= "
                f"{SIGMA_V0_COND_LIMIT:g} (docs/science.md#5-the-optimal-gain-k)",
            )
    for arr in (A, B, C):
        arr.setflags(write=False)
    return SystemSpec(name=name.strip(), A=A, B=B, C=C, sigma_u=sigma_u, sigma_v=sigma_v)
