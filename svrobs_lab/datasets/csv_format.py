"""CSV in long form, read as a stream (docs/datasets.md#csv).

One row per rollout and time step: a ``rollout`` column (any label; a rollout's
rows are consecutive), ``k`` (an integer growing by 1 from row to row within a
rollout), the state columns and the input columns. By default the states are
``x1..xn`` and the inputs ``u1..um`` (no other column allowed); the upload's
``state_columns`` / ``input_columns`` name them instead (other columns are then
ignored). The last row of a rollout carries its final state x_T: its input cells
are not read. Rows are numbered as the file's lines, the header being row 1.

Memory stays bounded: rows are read one at a time by the ``csv`` module and
converted to float64 in blocks of at least :data:`BLOCK_ROWS` rows (the finished
rollouts together; a longer rollout BLOCK_ROWS rows at a time), so the text of at
most three blocks is held, beside the arrays themselves (stacked: 8 bytes a rollout
beside its numbers) and a hash of each rollout's label (8 bytes); a file where two
labels have one hash is read a second time, keeping the labels, to name the repeated
one.
"""

from __future__ import annotations

import csv
import io
import itertools
import operator
import re
from array import array
from collections.abc import Callable
from typing import BinaryIO

import numpy as np

from svrobs_core.errors import SpecError

from .parsed import MAX_CHANNELS, MAX_ROLLOUTS, BadDatasetFile, DatasetOptions, Rollouts
from .parsed import check_names as _check_names
from .parsed import shown as quoted
from .stacked import RolloutStack

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
    start = stream.tell()
    try:
        return _read(stream, options, max_array_bytes, exact=False)
    except _Repeated:  # a label seen twice (or two labels of one hash): read it again
        stream.seek(start)
        return _read(stream, options, max_array_bytes, exact=True)


def _read(stream: BinaryIO, options: DatasetOptions, max_array_bytes: int, exact: bool) -> Rollouts:
    # bytes that are not UTF-8 become lone surrogates, found where they are used
    text = io.TextIOWrapper(stream, encoding="utf-8-sig", errors="surrogateescape", newline="")
    reader = None
    try:
        first = text.readline()
        if not first.strip():
            raise BadDatasetFile("the CSV file is empty (row 1 should be the header)")
        delim = max(DELIMITERS, key=first.count)
        reader = csv.reader(itertools.chain([first], text), delimiter=delim)
        return _Reader(reader, options, max_array_bytes, exact=exact).read()
    except csv.Error as exc:
        row = reader.line_num if reader is not None else 1
        raise BadDatasetFile(f"row {row}: {exc}") from None
    finally:
        text.detach()  # the caller's stream stays open


class _Repeated(Exception):
    """Two rollouts' labels have one hash: the file is read again, labels kept."""


class _Rollout:
    """The rollout being read: its rows are the last ones of the reader's lists."""

    __slots__ = ("label", "k0", "next_k", "x_parts", "u_parts")

    def __init__(self, label: str, k0: int):
        self.label, self.k0, self.next_k = label, k0, k0
        # float64 parts of a rollout of more than BLOCK_ROWS rows
        self.x_parts: list[np.ndarray] = []
        self.u_parts: list[np.ndarray] = []


class _Reader:
    """Rows -> rollouts stacked in blocks. The rows of finished rollouts are converted
    together, at least BLOCK_ROWS at a time (one block each time); a rollout of more
    than BLOCK_ROWS rows is converted BLOCK_ROWS rows at a time and is a block of its
    own. Each error is the one a reader converting every rollout when it is finished
    would give first: the pending rows are converted before any error is raised, and
    rollout by rollout when they hold one."""

    def __init__(self, reader, options: DatasetOptions, max_array_bytes: int, *, exact: bool):
        self.reader, self.options = reader, options
        self.max_values = max_array_bytes // 8
        self.values = 0
        # the labels seen (exact), else their hashes (8 bytes a rollout), checked at the end
        self.seen: set[str] | None = set() if exact else None
        self.hashes = array("q")
        self.rollouts = 0
        # the rows read and not converted: finished rollouts', then the current one's
        self.lines: list[int] = []
        # tuples of texts (the garbage collector leaves them once it has seen them)
        self.xs: list[tuple[str, ...]] = []
        self.us: list[tuple[str, ...]] = []  # a finished rollout's last row gives no input
        self.done: list[_Rollout] = []  # the finished rollouts among them
        self.done_rows: list[int] = []  # and their rows
        self.pending = 0  # the sum of done_rows
        # the stacked rollouts
        self.x_blocks: list[np.ndarray] = []
        self.u_blocks: list[np.ndarray] = []
        self.first = array("q", [0])  # the first rollout of each block, and the count
        self.bounds = array("q", [0])  # the first row of each rollout, and the rows

    def read(self) -> Rollouts:
        try:
            try:
                rollouts = self._read()
            except csv.Error:
                self.flush()  # the rollouts before the row the csv module refused
                raise
        except (BadDatasetFile, csv.Error):
            if self.repeated():
                raise _Repeated from None
            raise
        return rollouts

    def _read(self) -> Rollouts:
        reader = self.reader
        header = [h.strip() for h in next(reader)]
        bad = next((h for h in header if _not_utf8(h)), None)
        if bad is not None:
            raise BadDatasetFile(f"row 1 (the header): {_not_utf8(bad)}")
        ri, ki, sidx, snames, uidx, unames = _columns(header, self.options)
        self.snames, self.unames = snames, unames
        width = len(header)
        lines, xs, us = self.lines, self.xs, self.us
        states, inputs = _cells(sidx), _cells(uidx)
        current: _Rollout | None = None
        for row in reader:
            line = reader.line_num
            if len(row) != width:
                if not any(f.strip() for f in row):
                    continue  # a blank line
                raise self.refused(f"row {line}: {len(row)} fields, the header has {width}")
            label, ktext = row[ri].strip(), row[ki]
            if not INT_TEXT.fullmatch(ktext):
                what = _not_utf8(ktext) or (
                    "empty" if not ktext.strip() else f"{ktext.strip()!r} is not an integer"
                )
                raise self.refused(f"row {line}, column k: {what}")
            k = int(ktext)
            if current is None or label != current.label:
                if not label or _not_utf8(label):
                    what = _not_utf8(label) or "empty"
                    raise self.refused(f"row {line}, column rollout: {what}")
                if self.seen is None:
                    self.hashes.append(hash(label))  # a repeat is found at the end
                elif label in self.seen:
                    assert current is not None  # a label is seen once a rollout started
                    raise self.refused(
                        f"row {line}, column rollout: rollout {label} appears again after "
                        f"rollout {current.label}; the rows of a rollout must be consecutive"
                    )
                if current is not None:
                    self.finish(current)
                if self.rollouts >= MAX_ROLLOUTS:
                    raise self.refused(f"row {line}: more than {MAX_ROLLOUTS:,} rollouts")
                self.rollouts += 1
                if self.seen is not None:
                    self.seen.add(label)
                current = _Rollout(label, k)
            elif k != current.next_k:
                raise self.refused(
                    f"rollout {label}: k jumps from {current.next_k - 1} to {k} (row {line}); "
                    "k grows by 1 from row to row"
                )
            lines.append(line)
            xs.append(states(row))
            us.append(inputs(row))
            current.next_k += 1
            if len(lines) - self.pending > BLOCK_ROWS:
                self.flush()
                self.part(current, BLOCK_ROWS)  # the newest row may be the last one
        if current is None:
            raise BadDatasetFile("the CSV file has a header but no rows")
        self.finish(current)
        self.flush()
        if self.repeated():
            raise _Repeated
        self.hashes = array("q")
        X = RolloutStack(
            self.x_blocks,
            np.frombuffer(self.bounds, dtype=np.int64),
            np.frombuffer(self.first, dtype=np.int64),
            len(snames),
        )
        return Rollouts(
            X=X, U=X.fewer_rows(self.u_blocks, len(unames)), state_names=snames, input_names=unames
        )

    def refused(self, message: str) -> BadDatasetFile:
        """The error ``message``, once the finished rollouts are converted (an error
        in them comes first)."""
        self.flush()
        return BadDatasetFile(message)

    def finish(self, r: _Rollout) -> None:
        """The rollout ``r`` (its rows the last read) is finished."""
        rows = len(self.lines) - self.pending
        self.us.pop()  # its last row gives no input
        if r.x_parts:  # a long rollout: a block of its own (nothing before it pending)
            self.part(r, rows, last=True)
            x = _joined(r.x_parts)
            self.stack([x], [_joined(r.u_parts)], [len(x)])
            return
        self.done.append(r)
        self.done_rows.append(rows)
        self.pending += rows
        if rows < 2:
            raise self.refused(
                f"rollout {r.label}: 1 row; a rollout needs at least 2 states (rows)"
            )
        if self.pending >= BLOCK_ROWS:
            self.flush()

    def part(self, r: _Rollout, cut: int, *, last: bool = False) -> None:
        """Convert the first ``cut`` pending rows of the current rollout ``r`` (the
        only one pending); with ``last`` they end it."""
        k = r.next_k - len(self.lines)
        lines = self.lines[:cut]
        n_in = cut - 1 if last else cut
        r.x_parts.append(self.numbers(r.label, self.xs[:cut], lines, self.snames, k))
        r.u_parts.append(
            self.numbers(r.label, self.us[:n_in], lines[:n_in], self.unames, k, inputs=True)
        )
        del self.lines[:cut], self.xs[:cut], self.us[:n_in]

    def flush(self) -> None:
        """Convert the rows of the finished rollouts into one block."""
        if not self.done:
            return
        rows = self.pending
        inputs = rows - len(self.done)
        values = rows * len(self.snames) + inputs * len(self.unames)
        X = U = None
        if self.values + values <= self.max_values:
            try:
                X = _floats(self.xs[:rows], len(self.snames))
                U = _floats(self.us[:inputs], len(self.unames))
            except ValueError:
                pass
        if X is None or U is None or not (np.isfinite(X).all() and np.isfinite(U).all()):
            X, U = self.one_by_one()  # raises the error of the first rollout holding one
        else:
            self.values += values
        self.stack([X], [U], self.done_rows)
        del self.lines[:rows], self.xs[:rows], self.us[:inputs]
        self.done, self.done_rows, self.pending = [], [], 0

    def one_by_one(self) -> tuple[np.ndarray, np.ndarray]:
        """The pending finished rollouts converted one by one, as each was finished."""
        xs, us = [], []
        at = at_u = 0
        for r, rows in zip(self.done, self.done_rows):
            lines = self.lines[at : at + rows]
            xs.append(self.numbers(r.label, self.xs[at : at + rows], lines, self.snames, r.k0))
            us.append(
                self.numbers(
                    r.label,
                    self.us[at_u : at_u + rows - 1],
                    lines[:-1],
                    self.unames,
                    r.k0,
                    inputs=True,
                )
            )
            at, at_u = at + rows, at_u + rows - 1
        return np.concatenate(xs), np.concatenate(us)

    def stack(self, x: list[np.ndarray], u: list[np.ndarray], rows: list[int]) -> None:
        """A block of rollouts of ``rows`` rows each, and their inputs."""
        self.x_blocks += x
        self.u_blocks += u
        self.first.append(self.first[-1] + len(rows))
        end = self.bounds[-1]
        for r in rows:
            end += r
            self.bounds.append(end)

    def numbers(self, label, rows, lines, names, k: int, *, inputs: bool = False) -> np.ndarray:
        self.count(len(rows) * len(names))
        try:
            a = _floats(rows, len(names))
        except ValueError:
            _raise_not_number(rows, lines, names, inputs)
        bad = ~np.isfinite(a)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            what = "NaN" if np.isnan(a[r, c]) else "inf"
            raise BadDatasetFile(
                f"{what} at rollout {label}, k {k + r}, column {names[c]} "
                f"(row {lines[r]}: {rows[r][c].strip()!r})"
            )
        return a

    def count(self, values: int) -> None:
        self.values += values
        if self.values > self.max_values:
            raise BadDatasetFile(
                f"the arrays would take more than {self.max_values * 8 / 2**20:.0f} MB"
            )

    def repeated(self) -> bool:
        """Whether two rollouts' labels may be the same (two equal hashes)."""
        if len(self.hashes) < 2:
            return False
        h = np.frombuffer(self.hashes, dtype=np.int64)
        h.sort()  # in place: the hashes serve nothing else
        return bool((h[1:] == h[:-1]).any())


def _cells(columns: list[int]) -> Callable[[list[str]], tuple[str, ...]]:
    """The fields ``columns`` of a row, as a tuple."""
    if len(columns) > 1:
        return operator.itemgetter(*columns)
    if not columns:
        return lambda row: ()
    (i,) = columns
    return lambda row: (row[i],)


def _floats(rows: list[tuple[str, ...]], width: int) -> np.ndarray:
    """Rows of number texts -> (rows, width) float64; ValueError if one is not a number."""
    a = np.array(rows, dtype=np.float64)
    if a.shape != (len(rows), width):  # no rows; else a view would hold a second array object
        a = a.reshape(len(rows), width)
    return a


def _joined(parts: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(parts) if len(parts) > 1 else parts[0]


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
    seen: set[str] = set()
    for c in columns:
        if c not in index:
            raise SpecError(field, f"no column {quoted(c)} in the file's header ({shown})")
        if c in seen:
            raise SpecError(field, f"{quoted(c)} given twice")
        seen.add(c)
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
