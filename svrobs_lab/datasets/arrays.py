"""The variables of the array formats (NPZ, MATLAB, JSON) -> rollouts
(docs/datasets.md#npz): ``X`` (N, T+1, n) with ``U`` (N, T, m), or one pair per
rollout ``X_0, U_0, X_1, ...`` for rollouts of different lengths, beside optional
``sample_time``, ``state_names`` and ``input_names``. Each message names the
variable."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from .parsed import BadDatasetFile, Rollouts
from .stacked import RolloutStack

ALLOWED = "X, U (or X_0, U_0, X_1, ...), sample_time, state_names, input_names"
_PER_ROLLOUT = re.compile(r"([XU])_(0|[1-9][0-9]{0,6})", re.ASCII)
META = ("sample_time", "state_names", "input_names")


def numeric(name: str, value) -> np.ndarray:
    """A variable as float64 (integers converted); BadDatasetFile for anything else."""
    try:
        a = np.asarray(value)
    except (ValueError, TypeError):
        raise BadDatasetFile(f"{name}: expected numbers in rows of equal length") from None
    if a.dtype.kind == "c":
        raise BadDatasetFile(f"{name}: complex numbers are not accepted")
    if a.dtype.kind not in "iuf":
        raise BadDatasetFile(f"{name}: expected numbers, got {_kind(a)}")
    return a.astype(np.float64, copy=False)


def _kind(a: np.ndarray) -> str:
    return {"b": "booleans", "U": "text", "S": "bytes", "O": "objects"}.get(
        a.dtype.kind, f"dtype {a.dtype}"
    )


def split_variables(variables: Mapping) -> tuple[dict, dict, dict]:
    """(whole-array variables X/U, per-rollout {index: (X_i, U_i)}, metadata); an
    unknown variable, or both forms at once, is an error naming it."""
    whole: dict[str, Any] = {}
    per: dict[int, dict[str, Any]] = {}
    meta: dict[str, Any] = {}
    for key, value in variables.items():
        m = _PER_ROLLOUT.fullmatch(key)
        if key in ("X", "U"):
            whole[key] = value
        elif m:
            per.setdefault(int(m.group(2)), {})[m.group(1)] = value
        elif key in META:
            meta[key] = value
        else:
            raise BadDatasetFile(f"unknown variable {key!r}; expected {ALLOWED}")
    if whole and per:
        raise BadDatasetFile(
            f"both {sorted(whole)[0]} and {sorted(per[min(per)])[0]}_{min(per)}: give X and U, "
            "or X_0, U_0, X_1, ... (one pair per rollout), not both"
        )
    if "U" in whole and "X" not in whole:
        raise BadDatasetFile("U without X: X holds the states (N, T+1, n)")
    if not whole and not per:
        raise BadDatasetFile(f"no X variable; expected {ALLOWED}")
    return whole, per, meta


def whole_rollouts(X, U, *, matlab: bool = False) -> tuple[RolloutStack, RolloutStack]:
    """X (N, T+1, n) and U (N, T, m) or None (m = 0) -> the rollouts (one block each).

    ``matlab``: MATLAB drops trailing singleton dimensions, so a 2-D X is
    (N, T+1) with n = 1 and a 2-D U is (N, T) with m = 1."""
    X = numeric("X", X)
    if matlab and X.ndim == 2:
        X = X[:, :, None]
    if X.ndim != 3:
        raise BadDatasetFile(f"X: expected 3 dimensions (rollouts, T+1, n), got {X.ndim}")
    N, T1, n = X.shape
    if N == 0:
        raise BadDatasetFile("no rollouts")
    if T1 < 2:
        states = "state" if T1 == 1 else "states"
        raise BadDatasetFile(f"X: {T1} {states} per rollout; a rollout needs at least 2 states")
    if U is None or (matlab and np.size(U) == 0):
        U = np.zeros((N, T1 - 1, 0))
    U = numeric("U", U)
    if matlab and U.ndim == 2:
        U = U[:, :, None]
    if U.ndim != 3:
        raise BadDatasetFile(f"U: expected 3 dimensions (rollouts, T, m), got {U.ndim}")
    if U.shape[:2] != (N, T1 - 1):
        raise BadDatasetFile(
            f"U: shape {U.shape} does not match X {X.shape}: expected ({N}, {T1 - 1}, m)"
        )
    return _equal(X), _equal(U)


def _equal(a: np.ndarray) -> RolloutStack:
    """(N, rows, width) -> N rollouts of ``rows`` rows in one C-contiguous block."""
    N, rows, width = a.shape
    return RolloutStack.of_equal(np.ascontiguousarray(a).reshape(N * rows, width), N)


def ragged(arrays: list[np.ndarray]) -> RolloutStack:
    """Rollouts of their own arrays (checked: 2-D, one width) -> one block each."""
    return RolloutStack.of_arrays([np.ascontiguousarray(a) for a in arrays], arrays[0].shape[1])


def _underscore(var: str, i: int) -> str:
    return f"{var}_{i}"


def _cell(var: str, i: int) -> str:
    return f"{var}{{{i + 1}}}"  # MATLAB's 1-based cell index: X{1}


def per_rollout(
    per: dict, *, matlab: bool = False, name=_underscore
) -> tuple[RolloutStack, RolloutStack]:
    """{i: {"X": X_i, "U": U_i}} with i = 0..N-1 -> the rollouts (U_i absent
    everywhere: m = 0).
    ``name(var, i)``: how messages call rollout i's variable (X_3, or X{4} in a cell)."""
    count = max(per) + 1
    missing = next((i for i in range(count) if "X" not in per.get(i, {})), None)
    if missing is not None:
        raise BadDatasetFile(
            f"{name('X', missing)} is missing ({name('X', 0)} .. {name('X', count - 1)} "
            "are expected)"
        )
    with_u = [i for i in range(count) if "U" in per[i]]
    if with_u and len(with_u) != count:
        i = next(i for i in range(count) if "U" not in per[i])
        raise BadDatasetFile(f"{name('U', i)} is missing ({name('U', with_u[0])} is given)")
    X: list[np.ndarray] = []
    U: list[np.ndarray] = []
    for i in range(count):
        xname, uname = name("X", i), name("U", i)
        x = numeric(xname, per[i]["X"])
        if matlab and x.ndim == 1:
            x = x[:, None]
        if x.ndim != 2:
            raise BadDatasetFile(f"{xname}: expected 2 dimensions (T+1, n), got {x.ndim}")
        u = numeric(uname, per[i]["U"]) if with_u else np.zeros((0, 0))
        if u.size == 0 and (matlab or not with_u):
            u = np.zeros((max(x.shape[0] - 1, 0), 0))
        if u.ndim != 2:
            raise BadDatasetFile(f"{uname}: expected 2 dimensions (T, m), got {u.ndim}")
        check_pair(xname, uname, x, u, X, U)
        X.append(x)
        U.append(u)
    return ragged(X), ragged(U)


def check_pair(xname: str, uname: str, x: np.ndarray, u: np.ndarray, X: list, U: list) -> None:
    """One rollout's arrays agree with each other and with the rollouts before."""
    if x.shape[0] < 2:
        raise BadDatasetFile(f"{xname}: {x.shape[0]} state; a rollout needs at least 2 states")
    if u.shape[0] != x.shape[0] - 1:
        raise BadDatasetFile(
            f"{uname}: {u.shape[0]} rows; {xname} has {x.shape[0]} states, so {x.shape[0] - 1} "
            "inputs are expected"
        )
    if X and x.shape[1] != X[0].shape[1]:
        raise BadDatasetFile(
            f"{xname}: {x.shape[1]} states (columns); the first rollout has {X[0].shape[1]}"
        )
    if U and u.shape[1] != U[0].shape[1]:
        raise BadDatasetFile(
            f"{uname}: {u.shape[1]} inputs (columns); the first rollout has {U[0].shape[1]}"
        )


def sample_time_of(value) -> float | None:
    """A file's ``sample_time``: one positive finite number."""
    if value is None:
        return None
    a = np.asarray(value)
    if a.size != 1 or a.dtype.kind not in "iuf":
        raise BadDatasetFile("sample_time: expected one number")
    v = float(a.reshape(-1)[0])
    if not (math.isfinite(v) and v > 0):
        raise BadDatasetFile(f"sample_time: {v} is not a positive finite number")
    return v


def names_of(name: str, value) -> list[str] | None:
    """A file's channel names: strings (a text array, a MATLAB cell or char matrix)."""
    if value is None:
        return None
    a: list[Any] | np.ndarray
    if isinstance(value, list):  # a MATLAB cell read from HDF5
        a = value
    else:
        a = np.asarray(value, dtype=object).reshape(-1, order="F")
    out = []
    for v in a:
        while isinstance(v, np.ndarray) and v.dtype == object and v.size == 1:
            v = v.reshape(-1)[0]
        if isinstance(v, np.ndarray) and v.dtype.kind in "US" and v.size <= 1:
            v = v.reshape(-1)[0] if v.size else ""
        if isinstance(v, bytes):
            v = v.decode("utf-8", "replace")
        if not isinstance(v, str):
            raise BadDatasetFile(f"{name}: expected text, got {type(v).__name__}")
        out.append(v)
    return out


def rollouts_of(variables: Mapping, *, matlab: bool = False) -> Rollouts:
    """The rollouts of a file's variables (already numpy arrays or MATLAB cells as
    lists of arrays)."""
    whole, per, meta = split_variables(variables)
    if whole:
        X, U = whole["X"], whole.get("U")
        if isinstance(X, list):  # a MATLAB cell array: one rollout per cell
            if not X:
                raise BadDatasetFile("X: an empty cell array (no rollouts)")
            per = {i: {"X": x} for i, x in enumerate(X)}
            if U is not None and not (isinstance(U, np.ndarray) and U.size == 0):
                if not isinstance(U, list) or len(U) != len(X):
                    raise BadDatasetFile(
                        f"U: expected a cell array of {len(X)} input arrays, like X"
                    )
                for i, u in enumerate(U):
                    per[i]["U"] = u
            Xs, Us = per_rollout(per, matlab=matlab, name=_cell)
        else:
            if isinstance(U, list):
                raise BadDatasetFile("U: a cell array, but X is a numeric array")
            Xs, Us = whole_rollouts(X, U, matlab=matlab)
    else:
        Xs, Us = per_rollout(per, matlab=matlab)
    return Rollouts(
        X=Xs,
        U=Us,
        state_names=names_of("state_names", meta.get("state_names")),
        input_names=names_of("input_names", meta.get("input_names")),
        sample_time=sample_time_of(meta.get("sample_time")),
    )
