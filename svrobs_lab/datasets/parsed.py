"""A parsed dataset: rollouts as float64 arrays, channel names, shapes and per-channel
statistics (docs/datasets.md#the-data-model), and the checks every format shares.

Every format's parser ends in :func:`build`, which checks what all formats must hold
(at least one rollout, each with at least 2 states, every value finite, the names
of the right count) and computes the statistics. A bad file raises
:class:`~svrobs_lab.errors.BadDatasetFile` (an invalid request naming the form
field ``file``), whose message names the row, column or variable.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np

from svrobs_core.errors import SpecError
from svrobs_core.measured.rollout_lists import RolloutLists
from svrobs_core.text import printable

from ..errors import BadDatasetFile
from .stacked import RolloutStack, channel_stats, first_misshapen, first_not_finite

MAX_CHANNELS = 50  # n and m: the state dimension the core accepts (svrobs_core.spec)
MAX_ROLLOUTS = 1_000_000
MAX_NAME = 64  # characters of a channel name
FORMATS = ("csv", "npz", "mat", "mat73", "json")


@dataclass(frozen=True, kw_only=True)
class DatasetOptions:
    """What the upload declares beside the file (docs/datasets.md#upload-fields):
    the CSV columns of the states and inputs, channel names for the array formats,
    the sample time."""

    state_columns: tuple[str, ...] | None = None
    input_columns: tuple[str, ...] | None = None
    state_names: tuple[str, ...] | None = None
    input_names: tuple[str, ...] | None = None
    sample_time: float | None = None


@dataclass(frozen=True, kw_only=True, eq=False)
class ParsedDataset(RolloutLists):
    """Rollouts ``X[i]`` of shape (T_i + 1, n) and inputs ``U[i]`` of shape (T_i, m)
    (m may be 0), float64 and finite, stacked (views of one rollout made when asked
    for); the sha256 and size of the original bytes."""

    X: RolloutStack
    U: RolloutStack
    state_names: list[str]
    input_names: list[str]
    sample_time: float | None
    format: str
    sha256: str
    size_bytes: int
    stats: dict

    @property
    def lengths(self) -> list[int]:
        """T_i of every rollout: its number of steps (it has T_i + 1 states)."""
        return self.U.lengths.tolist()

    @property
    def samples(self) -> int:
        """The sum of the T_i."""
        return self.U.rows

    def arrays(self) -> list[np.ndarray]:
        """The stored form's arrays: every rollout's states, then every rollout's
        inputs, back to back (the blocks)."""
        return [*self.X.blocks, *self.U.blocks]


@dataclass(frozen=True, kw_only=True)
class Rollouts:
    """What a format's reader returns: the arrays and whatever names the file holds."""

    X: RolloutStack
    U: RolloutStack
    state_names: Sequence[str] | None = None
    input_names: Sequence[str] | None = None
    sample_time: float | None = None


def default_names(prefix: str, count: int) -> list[str]:
    return [f"{prefix}{i + 1}" for i in range(count)]


SHOWN = 80  # characters of a refused value quoted in a message


def shown(text: str) -> str:
    """``text`` quoted for a message, cut after :data:`SHOWN` characters."""
    if len(text) <= SHOWN:
        return repr(text)
    return f"{text[:SHOWN]!r}... (cut, {len(text):,} characters)"


def name_refused(text: str) -> str:
    """The message refusing ``text`` as a channel or system name."""
    return f"{shown(text)}: a name is 1 to {MAX_NAME} printable characters"


def check_names(names: Sequence[str], field: str, count: int | None = None) -> list[str]:
    """Channel names: ``count`` of them if given, unique, 1-64 printable characters.
    ``field``: the upload field, or ``"file: <where>"`` for names read from the file."""

    def error(message: str) -> SpecError:
        if field.startswith("file: "):
            return BadDatasetFile(f"{field[6:]}: {message}")
        return SpecError(field, message)

    names = [str(v).strip() for v in names]
    if count is not None and len(names) != count:
        raise error(f"{len(names)} names for {count} channels")
    for v in names:
        if not v or len(v) > MAX_NAME or not printable(v):
            raise error(name_refused(v))
    dup = next((v for i, v in enumerate(names) if v in names[:i]), None)
    if dup is not None:
        raise error(f"{dup!r} appears twice")
    return names


def check_finite(stack: RolloutStack, names: list[str]) -> None:
    """BadDatasetFile naming the first NaN or inf (rollout, k, column)."""
    found = first_not_finite(stack)
    if found is not None:
        i, r, c = found
        what = "NaN" if math.isnan(stack[i][r, c]) else "inf"
        raise BadDatasetFile(f"{what} at rollout {i}, k {r}, column {names[c]}")


def build(
    rollouts: Rollouts,
    options: DatasetOptions,
    *,
    fmt: str,
    sha256: str,
    size_bytes: int,
    names_in_file: bool = False,
) -> ParsedDataset:
    """Check the arrays every format yields and compute the statistics. Names: the
    upload's ``state_names`` / ``input_names``, else the file's, else x1..xn, u1..um
    (``names_in_file``: the names are the CSV columns, already checked)."""
    X, U = rollouts.X, rollouts.U
    if not len(X):
        raise BadDatasetFile("no rollouts")
    if len(X) > MAX_ROLLOUTS:
        raise BadDatasetFile(f"{len(X):,} rollouts; at most {MAX_ROLLOUTS:,}")
    n, m = X.width, U.width
    if n < 1:
        raise BadDatasetFile("no state columns (n = 0)")
    if n > MAX_CHANNELS or m > MAX_CHANNELS:
        raise BadDatasetFile(f"n = {n}, m = {m}: at most {MAX_CHANNELS} states and inputs")
    _check_lengths(X, U)
    if names_in_file:
        # the CSV's columns: both given
        state_names = list(cast("Sequence[str]", rollouts.state_names))
        input_names = list(cast("Sequence[str]", rollouts.input_names))
    else:
        state_names = _names(options.state_names, rollouts.state_names, "state_names", "x", n)
        input_names = _names(options.input_names, rollouts.input_names, "input_names", "u", m)
    check_finite(X, state_names)
    check_finite(U, input_names)
    sample_time = options.sample_time if options.sample_time is not None else rollouts.sample_time
    return ParsedDataset(
        X=X,
        U=U,
        state_names=state_names,
        input_names=input_names,
        sample_time=sample_time,
        format=fmt,
        sha256=sha256,
        size_bytes=size_bytes,
        stats={"states": channel_stats(X, state_names), "inputs": channel_stats(U, input_names)},
    )


def _names(given, in_file, field: str, prefix: str, count: int) -> list[str]:
    if given is not None:
        return check_names(given, field, count)
    if in_file is not None:
        return check_names(in_file, f"file: {field}", count)
    return default_names(prefix, count)


def _check_lengths(X: RolloutStack, U: RolloutStack) -> None:
    """Every rollout has at least 2 states and one input fewer (the first one that
    does not is named)."""
    if len(U) != len(X):
        raise BadDatasetFile(f"{len(X)} state rollouts and {len(U)} input rollouts")
    i = first_misshapen(X, U)
    if i is None:
        return
    x, u = X[i], U[i]
    if x.shape[0] < 2:
        raise BadDatasetFile(f"rollout {i}: {x.shape[0]} state; a rollout needs at least 2 states")
    raise BadDatasetFile(
        f"rollout {i}: states {x.shape} and inputs {u.shape} do not make "
        f"(T + 1, {X.width}) and (T, {U.width})"
    )
