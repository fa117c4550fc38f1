"""CSV in long form, read as a stream (docs/datasets.md#csv).

One row per rollout and time step: a ``rollout`` column (any label; a rollout's
rows are consecutive), ``k`` (an integer growing by 1 from row to row within a
rollout), the state columns and the input columns. By default the states are
``x1..xn`` and the inputs ``u1..um`` (no other column allowed); the upload's
``state_columns`` / ``input_columns`` name them instead (other columns are then
ignored). The last row of a rollout carries its final state x_T: its input cells
are not read. Rows are numbered as the file's lines, the header being row 1.

Memory stays bounded: rows are read one at a time by the ``csv`` module and
converted to float64 in blocks of :data:`BLOCK_ROWS`, so the text of at most one
block is held, beside the arrays themselves.
"""

from __future__ import annotations

import csv
import io
import itertools
import re
from typing import BinaryIO

import numpy as np

from svrobs_core.errors import SpecError

from .parsed import MAX_CHANNELS, MAX_ROLLOUTS, BadDatasetFile, DatasetOptions, Rollouts
from .parsed import check_names as _check_names
from .parsed import shown as quoted

BLOCK_ROWS = 4096
DELIMITERS = (",", ";", "\t")
INT_TEXT = re.compile(r"\s*-?[0-9]{1,18}\s*", re.ASCII)
_NOT_UTF8 = re.compile(r"[\udc80-\udcff]")


def _not_utf8(text: str) -> str | None:
    """The message for a field holding bytes that are not UTF-8, else None."""
    m = _NOT_UTF8.search(text)
    return None if m is None else f"not UTF-8 text (byte 0x{ord(m.group()) - 0xDC00:02x})"


def read_csv(stream: BinaryIO, options: DatasetOptions, *, max_array_bytes: int) -> Rollouts:
    """The rollouts of a long-form CSV file (UTF-8, an optional BOM; the delimiter is
    the most frequent of ``,`` ``;`` and tab in the header)."""
    # bytes that are not UTF-8 become lone surrogates, found where they are used
    text = io.TextIOWrapper(stream, encoding="utf-8-sig", errors="surrogateescape", newline="")
    reader = None
    try:
        first = text.readline()
        if not first.strip():
            raise BadDatasetFile("the CSV file is empty (row 1 should be the header)")
        delim = max(DELIMITERS, key=first.count)
        reader = csv.reader(itertools.chain([first], text), delimiter=delim)
        return _Reader(reader, options, max_array_bytes).read()
    except csv.Error as exc:
        row = reader.line_num if reader is not None else 1
        raise BadDatasetFile(f"row {row}: {exc}") from None
    finally:
        text.detach()  # the caller's stream stays open


class _Reader:
    def __init__(self, reader, options: DatasetOptions, max_array_bytes: int):
        self.reader, self.options = reader, options
        self.max_values = max_array_bytes // 8
        self.values = 0

    def read(self) -> Rollouts:
        reader = self.reader
        header = [h.strip() for h in next(reader)]
        bad = next((h for h in header if _not_utf8(h)), None)
        if bad is not None:
            raise BadDatasetFile(f"row 1 (the header): {_not_utf8(bad)}")
        ri, ki, sidx, snames, uidx, unames = _columns(header, self.options)
        width = len(header)
        # each finished rollout keeps only (X, U, label, first k): its reader, some 1 kB,
        # is let go (files of many short rollouts)
        done: list[tuple[np.ndarray, np.ndarray, str, int]] = []
        seen: set[str] = set()
        current: _Rollout | None = None
        for row in reader:
            line = reader.line_num
            if len(row) != width:
                if not any(f.strip() for f in row):
                    continue  # a blank line
                raise BadDatasetFile(f"row {line}: {len(row)} fields, the header has {width}")
            label, ktext = row[ri].strip(), row[ki]
            if not INT_TEXT.fullmatch(ktext):
                what = _not_utf8(ktext) or (
                    "empty" if not ktext.strip() else f"{ktext.strip()!r} is not an integer"
                )
                raise BadDatasetFile(f"row {line}, column k: {what}")
            k = int(ktext)
            if current is None or label != current.label:
                if not label or _not_utf8(label):
                    what = _not_utf8(label) or "empty"
                    raise BadDatasetFile(f"row {line}, column rollout: {what}")
                if label in seen:
                    assert current is not None  # a label is seen once a rollout started
                    raise BadDatasetFile(
                        f"row {line}, column rollout: rollout {label} appears again after "
                        f"rollout {current.label}; the rows of a rollout must be consecutive"
                    )
                if current is not None:
                    done.append(current.finish().kept())
                if len(seen) >= MAX_ROLLOUTS:
                    raise BadDatasetFile(f"row {line}: more than {MAX_ROLLOUTS:,} rollouts")
                seen.add(label)
                current = _Rollout(self, label, k, snames, unames)
            elif k != current.next_k:
                raise BadDatasetFile(
                    f"rollout {label}: k jumps from {current.next_k - 1} to {k} (row {line}); "
                    "k grows by 1 from row to row"
                )
            current.add(line, [row[i] for i in sidx], [row[i] for i in uidx])
        if current is None:
            raise BadDatasetFile("the CSV file has a header but no rows")
        done.append(current.finish().kept())
        X, U, labels, first_k = zip(*done)
        return Rollouts(
            X=list(X),
            U=list(U),
            state_names=snames,
            input_names=unames,
            labels=list(labels),
            first_k=list(first_k),
        )

    def count(self, values: int) -> None:
        self.values += values
        if self.values > self.max_values:
            raise BadDatasetFile(
                f"the arrays would take more than {self.max_values * 8 / 2**20:.0f} MB"
            )


class _Rollout:
    """One rollout's rows: text of at most BLOCK_ROWS rows, then float64 parts."""

    X: np.ndarray  # the states and inputs, set by finish()
    U: np.ndarray

    def __init__(self, owner: _Reader, label: str, k0: int, snames, unames):
        self.owner, self.label, self.k0, self.next_k = owner, label, k0, k0
        self.snames, self.unames = snames, unames
        self.lines: list[int] = []
        self.xs: list[list[str]] = []
        self.us: list[list[str]] = []
        self.x_parts: list[np.ndarray] = []
        self.u_parts: list[np.ndarray] = []

    def add(self, line: int, xs: list[str], us: list[str]) -> None:
        self.lines.append(line)
        self.xs.append(xs)
        self.us.append(us)
        self.next_k += 1
        if len(self.lines) > BLOCK_ROWS:
            self._convert(len(self.lines) - 1)  # the newest row may be the last one

    def _convert(self, cut: int, *, last: bool = False) -> None:
        """Rows [0, cut) to float64; with ``last`` the final row gives no input."""
        k = self.next_k - len(self.lines)
        lines = self.lines[:cut]
        self.x_parts.append(self._numbers(self.xs[:cut], lines, self.snames, k))
        n_in = cut - 1 if last else cut
        self.u_parts.append(
            self._numbers(self.us[:n_in], lines[:n_in], self.unames, k, inputs=True)
        )
        del self.lines[:cut], self.xs[:cut], self.us[:cut]

    def _numbers(self, rows, lines, names, k: int, *, inputs: bool = False) -> np.ndarray:
        self.owner.count(len(rows) * len(names))
        shape = (len(rows), len(names))
        try:
            a = np.array(rows, dtype=np.float64)
            if a.shape != shape:  # no rows; else a view would hold a second array object
                a = a.reshape(shape)
        except ValueError:
            _raise_not_number(rows, lines, names, inputs)
        bad = ~np.isfinite(a)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            what = "NaN" if np.isnan(a[r, c]) else "inf"
            raise BadDatasetFile(
                f"{what} at rollout {self.label}, k {k + r}, column {names[c]} "
                f"(row {lines[r]}: {rows[r][c].strip()!r})"
            )
        return a

    def kept(self) -> tuple[np.ndarray, np.ndarray, str, int]:
        """What the dataset keeps of this finished rollout."""
        return self.X, self.U, self.label, self.k0

    def finish(self) -> _Rollout:
        self._convert(len(self.lines), last=True)
        self.X = np.concatenate(self.x_parts) if len(self.x_parts) > 1 else self.x_parts[0]
        self.U = np.concatenate(self.u_parts) if len(self.u_parts) > 1 else self.u_parts[0]
        self.x_parts = self.u_parts = []
        if self.X.shape[0] < 2:
            raise BadDatasetFile(
                f"rollout {self.label}: 1 row; a rollout needs at least 2 states (rows)"
            )
        return self


def _raise_not_number(rows, lines, names, inputs: bool):
    """BadDatasetFile naming the first cell of ``rows`` that float() cannot read."""
    for row, line in zip(rows, lines):
        for text, name in zip(row, names):
            try:
                float(text)
            except ValueError:
                if _not_utf8(text):
                    raise BadDatasetFile(f"row {line}, column {name}: {_not_utf8(text)}") from None
                if text.strip():
                    raise BadDatasetFile(
                        f"row {line}, column {name}: {text.strip()!r} is not a number"
                    ) from None
                hint = " (only a rollout's last row may leave its inputs empty)" if inputs else ""
                raise BadDatasetFile(f"row {line}, column {name}: empty{hint}") from None
    raise BadDatasetFile(f"rows {lines[0]}-{lines[-1]}: not numbers")


def _columns(header: list[str], options: DatasetOptions):
    """(rollout index, k index, state indices, state names, input indices, input names)."""
    shown = ", ".join(header[:12]) + (", ..." if len(header) > 12 else "")
    index: dict[str, int] = {}
    for i, h in enumerate(header):
        index.setdefault(h, i)
    for need in ("rollout", "k"):
        if need not in index:
            raise BadDatasetFile(f"header: no {need!r} column (the header is: {shown})")
    explicit = options.state_columns is not None or options.input_columns is not None
    states = _chosen(options.state_columns, "state_columns", index, shown)
    if states is None:
        states = _convention(header, "x", "state")
        if not states:
            raise BadDatasetFile(
                f"header: no state columns x1..xn (the header is: {shown}); "
                "name them with state_columns"
            )
    inputs = _chosen(options.input_columns, "input_columns", index, shown)
    if inputs is None:
        inputs = _convention(header, "u", "input")
    for c in states:
        if c in ("rollout", "k"):
            raise SpecError("state_columns", f"{quoted(c)} is the {c} column, not a state")
    for c in inputs:
        if c in ("rollout", "k"):
            raise SpecError("input_columns", f"{quoted(c)} is the {c} column, not an input")
        if c in states:
            raise SpecError("input_columns", f"{quoted(c)} is also a state column")
    if len(states) > MAX_CHANNELS or len(inputs) > MAX_CHANNELS:
        raise BadDatasetFile(
            f"header: {len(states)} state and {len(inputs)} input columns; "
            f"at most {MAX_CHANNELS} of each"
        )
    used = ["rollout", "k", *states, *inputs]
    for c in used:
        if header.count(c) > 1:
            raise BadDatasetFile(f"header: column {quoted(c)} appears twice")
    if not explicit:
        other = next((h for h in header if h not in used), None)
        if other is not None:
            raise BadDatasetFile(
                f"header: column {quoted(other)} is not rollout, k, x1..xn or u1..um; name the "
                "state and input columns with state_columns and input_columns"
            )
    snames = _check_names(states, "file: header")
    unames = _check_names(inputs, "file: header")
    return (
        index["rollout"],
        index["k"],
        [index[c] for c in states],
        snames,
        [index[c] for c in inputs],
        unames,
    )


def _chosen(columns, field: str, index: dict, shown: str) -> list[str] | None:
    if columns is None:
        return None
    for c in columns:
        if c not in index:
            raise SpecError(field, f"no column {quoted(c)} in the file's header ({shown})")
    return list(columns)


def _convention(header: list[str], prefix: str, what: str) -> list[str]:
    """The columns prefix1..prefixK in number order (SpecError if one is missing)."""
    pattern = re.compile(rf"{prefix}([1-9][0-9]*)", re.ASCII)
    numbers = sorted(int(m.group(1)) for h in header if (m := pattern.fullmatch(h)))
    missing = next((i for i, v in enumerate(numbers, start=1) if v != i), None)
    if missing is not None:
        raise BadDatasetFile(
            f"header: {what} column {prefix}{missing} is missing "
            f"({', '.join(f'{prefix}{v}' for v in numbers[:8])} given)"
        )
    return [f"{prefix}{v}" for v in numbers]
