"""JSON for small sets (docs/datasets.md#json): ``{"X": [rollout, ...], "U": [...],
"sample_time": ..., "state_names": [...], "input_names": [...]}``, a rollout being a
list of rows (one list of numbers per time step). At most :data:`MAX_JSON_BYTES` and
:data:`MAX_JSON_LISTS` lists (rows and rollouts): a parsed list takes some 60-90 bytes
of memory, so the lists are counted in the bytes before the file is parsed."""

from __future__ import annotations

import json
import sys
from typing import BinaryIO

import numpy as np

from .arrays import check_pair, names_of, sample_time_of
from .parsed import BadDatasetFile, Rollouts

MAX_JSON_BYTES = 32 * 2**20
MAX_JSON_LISTS = 2_000_000
KEYS = ("X", "U", "sample_time", "state_names", "input_names")


def _no_constant(name: str):
    raise BadDatasetFile(f"{name} is not a number JSON allows; every value must be finite")


def read_json(stream: BinaryIO, *, size: int) -> Rollouts:
    if size > MAX_JSON_BYTES:
        raise BadDatasetFile(
            f"a JSON dataset is at most {MAX_JSON_BYTES // 2**20} MB; upload larger sets "
            "as CSV, NPZ or MAT"
        )
    raw = stream.read()
    lists = raw.count(b"[")  # an upper bound: a "[" inside a name counts too
    if lists > MAX_JSON_LISTS:
        raise BadDatasetFile(
            f"a JSON dataset has at most {MAX_JSON_LISTS:,} lists (rows and rollouts), this "
            f"one about {lists:,}; upload larger sets as CSV, NPZ or MAT"
        )
    try:
        obj = json.loads(raw.decode("utf-8-sig"), parse_constant=_no_constant)
    except UnicodeDecodeError as exc:
        raise BadDatasetFile(f"not UTF-8 text (byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise BadDatasetFile(
            f"not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}"
        ) from None
    except RecursionError:
        raise BadDatasetFile("not valid JSON: nested too deeply") from None
    except BadDatasetFile:
        raise
    except ValueError:  # an integer longer than int() converts
        raise BadDatasetFile(
            f"an integer of more than {sys.get_int_max_str_digits():,} digits "
            "(a float64 is at most about 1.8e308)"
        ) from None
    if not isinstance(obj, dict):
        raise BadDatasetFile('a JSON dataset is an object {"X": [...], "U": [...]}')
    unknown = next((k for k in obj if k not in KEYS), None)
    if unknown is not None:
        raise BadDatasetFile(f"unknown key {unknown!r}; expected {', '.join(KEYS)}")
    xs = obj.get("X")
    if not isinstance(xs, list) or not xs:
        raise BadDatasetFile("X: expected a list of rollouts (each a list of state rows)")
    us = obj.get("U")
    if us is not None and (not isinstance(us, list) or len(us) != len(xs)):
        raise BadDatasetFile(f"U: expected a list of {len(xs)} rollouts, like X")
    X: list[np.ndarray] = []
    U: list[np.ndarray] = []
    # each rollout's lists are let go once converted: the parsed JSON (tens of bytes per
    # number as Python lists) and the arrays are not both held whole
    for i, x in enumerate(xs):
        xs[i] = None
        x = _matrix(f"X[{i}]", x)
        u = _matrix(f"U[{i}]", us[i]) if us is not None else np.zeros((0, 0))
        if us is not None:
            us[i] = None
        if u.size == 0:
            u = np.zeros((max(x.shape[0] - 1, 0), 0))
        check_pair(f"X[{i}]", f"U[{i}]", x, u, X, U)
        X.append(x)
        U.append(u)
    for key in ("state_names", "input_names"):
        if key in obj and not (
            isinstance(obj[key], list) and all(isinstance(v, str) for v in obj[key])
        ):
            raise BadDatasetFile(f"{key}: expected a list of strings")
    st = obj.get("sample_time")
    if st is not None and (isinstance(st, bool) or not isinstance(st, (int, float))):
        raise BadDatasetFile("sample_time: expected one number")
    return Rollouts(
        X=X,
        U=U,
        state_names=names_of("state_names", obj.get("state_names")),
        input_names=names_of("input_names", obj.get("input_names")),
        sample_time=sample_time_of(st),
    )


def _matrix(name: str, rows) -> np.ndarray:
    """A list of equally long lists of numbers -> (rows, cols) float64."""
    if not isinstance(rows, list):
        raise BadDatasetFile(f"{name}: expected a list of rows (lists of numbers)")
    width = None
    for r, row in enumerate(rows):
        if not isinstance(row, list):
            raise BadDatasetFile(f"{name}[{r}]: expected a list of numbers")
        if width is None:
            width = len(row)
        elif len(row) != width:
            raise BadDatasetFile(f"{name}[{r}]: {len(row)} numbers, {name}[0] has {width}")
        for c, v in enumerate(row):
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise BadDatasetFile(f"{name}[{r}][{c}]: {json.dumps(v)} is not a number")
    try:
        return np.array(rows, dtype=np.float64).reshape(len(rows), width or 0)
    except OverflowError:
        raise BadDatasetFile(f"{name}: an integer too large for a float64") from None
