"""JSON for small sets (docs/datasets.md#json): ``{"X": [rollout, ...], "U": [...],
"sample_time": ..., "state_names": [...], "input_names": [...]}``, a rollout being a
list of rows (one list of numbers per time step). At most :data:`MAX_JSON_BYTES` and
:data:`MAX_JSON_LISTS` lists (rows and rollouts).

A file of X (and U) as lists of rollouts of rows of numbers is read rollout by rollout
(:func:`_streamed`): it takes about its text and its arrays in memory. Any other file
(one with an error to name, a key given twice, empty inputs) is parsed whole by
``json.loads`` (:func:`_loaded`), where a parsed list takes some 60-90 bytes of
memory: so the lists are counted in the bytes before the file is parsed."""

from __future__ import annotations

import itertools
import json
import re
from array import array
from typing import BinaryIO

import numpy as np

from .. import json_text
from .arrays import check_pair, names_of, ragged, sample_time_of
from .parsed import BadDatasetFile, Rollouts
from .stacked import RolloutStack, first_misshapen

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
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise BadDatasetFile(f"not UTF-8 text (byte {exc.start})") from None
    del raw
    return _streamed(text) or _loaded(text)


def _loaded(text: str) -> Rollouts:
    """The file parsed whole by ``json.loads``, then checked rollout by rollout: what
    gives every error its message (and reads the files :func:`_streamed` leaves)."""
    try:
        obj = json_text.loads(text, parse_constant=_no_constant)
    except BadDatasetFile:
        raise
    except ValueError as exc:
        raise BadDatasetFile(str(exc)) from None
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
    return _with_meta(ragged(X), ragged(U), obj)


def _with_meta(X: RolloutStack, U: RolloutStack, obj: dict) -> Rollouts:
    """The rollouts with the file's names and sample time (checked)."""
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


class _Leave(Exception):
    """Not a file :func:`_streamed` reads: :func:`_loaded` reads it, or names its error."""


_WS = re.compile(r"[ \t\n\r]*")
_NUMBER = r"-?(?:0|[1-9][0-9]*)(?:\.[0-9]+)?(?:[eE][-+]?[0-9]+)?"  # JSON's, as json reads it
_SEP = r"[ \t\n\r]*,[ \t\n\r]*"
_ROW = rf"\[[ \t\n\r]*(?:{_NUMBER}(?:{_SEP}{_NUMBER})*+)?+[ \t\n\r]*\]"
# a rollout: a list of rows of numbers; rows hold no bracket, so "[" counts them
_ROLLOUT = re.compile(rf"\[[ \t\n\r]*(?:{_ROW}(?:{_SEP}{_ROW})*+)?+[ \t\n\r]*\]", re.ASCII)
PIECE_CHARS = 1 << 14  # text of rows converted at a time


def _streamed(text: str) -> Rollouts | None:
    """The rollouts of a file holding X and U as lists of rollouts of rows of numbers,
    each at least 2 states (T inputs beside T + 1 states), every key once: read rollout
    by rollout, never as Python lists all at once (json reads each piece of rows, so
    each number is the one ``json.loads`` gives). None for any other file."""
    try:
        found = _top_level(text)
    except (_Leave, ValueError, StopIteration, RecursionError, OverflowError, BadDatasetFile):
        return None  # json errors are ValueError, and an integer too long for int() too
    X = found.get("X")
    if not isinstance(X, RolloutStack):
        return None
    U = found.get("U")
    if U is None:
        per_block = np.diff(X.first).tolist()
        blocks = [np.zeros((len(b) - count, 0)) for b, count in zip(X.blocks, per_block)]
        U = X.fewer_rows(blocks, 0)
    elif not isinstance(U, RolloutStack):
        return None
    if len(U) != len(X) or first_misshapen(X, U) is not None:
        return None  # not T inputs beside T + 1 states, T >= 1
    if U.bounds is not X.bounds:  # U before X: U's rows counted by X's bounds
        U = RolloutStack(U.blocks, X.bounds, U.first, U.width, less=1)
    return _with_meta(X, U, found)


def _top_level(text: str) -> dict:
    """The object's values: X and U as stacks, the others as json reads them."""
    scan = vars(json.JSONDecoder(parse_constant=_no_constant))["scan_once"]  # json's own
    found: dict = {}
    pos = _expect(text, _blank(text, 0), "{")
    while True:
        if text.startswith("}", pos) and not found:
            raise _Leave  # an empty object
        if not text.startswith('"', pos):
            raise _Leave
        key, pos = scan(text, pos)
        pos = _expect(text, pos, ":")
        if key in found or key not in KEYS:
            raise _Leave
        if key in ("X", "U"):
            found[key], pos = _stack(text, pos, found.get("X") if key == "U" else None)
        else:
            found[key], pos = scan(text, pos)
        pos = _blank(text, pos)
        if text.startswith("}", pos):
            break
        pos = _expect(text, pos, ",")
    if _blank(text, pos + 1) != len(text):
        raise _Leave
    return found


def _blank(text: str, pos: int) -> int:
    """The position after the blanks at ``pos``."""
    m = _WS.match(text, pos)
    return pos if m is None else m.end()


def _expect(text: str, pos: int, char: str) -> int:
    """The position after ``char`` and the blanks after it, at ``pos`` after blanks."""
    pos = _blank(text, pos)
    if not text.startswith(char, pos):
        raise _Leave
    return _blank(text, pos + 1)


def _stack(text: str, pos: int, states: RolloutStack | None) -> tuple[RolloutStack, int]:
    """A list of rollouts at ``pos`` -> (the rollouts, the position after it); with
    ``states``, the inputs of those rollouts (each one row fewer)."""
    pos = _expect(text, pos, "[")
    rows = _Rows(text, states)
    while True:
        m = _ROLLOUT.match(text, pos)
        if m is None:
            raise _Leave
        rows.add(m.start(), m.end())
        pos = _blank(text, m.end())
        if text.startswith("]", pos):
            return rows.stack(), pos + 1
        pos = _expect(text, pos, ",")


class _Rows:
    """The rows of rollouts (spans of ``text``) -> float64 blocks: short rollouts
    together, a long one piece by piece into its own block."""

    def __init__(self, text: str, states: RolloutStack | None = None):
        self.text = text
        # the stacked states these rows are the inputs of: their bounds count the rows
        self.states = states
        self.state_bounds = states.bounds.data if states is not None else None
        self.rollouts = 0
        self.width: int | None = None
        self.start = self.end = self.pending = 0  # text[start:end]: rollouts not converted
        self.blocks: list[np.ndarray] = []
        self.first = array("q", [0])  # the first rollout of each block, and the count
        self.bounds = array("q", [0])  # the first row of each rollout, and the rows

    def add(self, start: int, end: int) -> None:
        """The rollout ``text[start:end]`` (``[row, row, ...]``)."""
        count = self.text.count("[", start + 1, end)
        if count < 1:
            raise _Leave  # no rows
        i, known = self.rollouts, self.state_bounds
        if known is None:
            self.bounds.append(self.bounds[-1] + count)
        elif i + 1 >= len(known) or count != known[i + 1] - known[i] - 1:
            raise _Leave  # not the inputs of the states
        self.rollouts += 1
        if end - start > PIECE_CHARS:
            self.flush()
            self.block(self.long(start, end, count), 1)
            return
        if not self.pending:
            self.start = start
        self.end, self.pending = end, self.pending + 1
        if end - self.start >= PIECE_CHARS:
            self.flush()

    def flush(self) -> None:
        """Convert the pending rollouts (one after the other in the text) into a block."""
        if self.pending:
            rollouts = json.loads("[" + self.text[self.start : self.end] + "]")
            self.block(self.floats(list(itertools.chain.from_iterable(rollouts))), self.pending)
            self.pending = 0

    def long(self, start: int, end: int, count: int) -> np.ndarray:
        """The rollout ``text[start:end]`` of ``count`` rows, converted piece by piece."""
        text = self.text
        first, last = text.find("[", start + 1, end), text.rfind("]", start, end - 1) + 1
        out = None
        at = 0
        while first < last:
            stop = text.find("]", min(first + PIECE_CHARS, last - 1)) + 1
            a = self.floats(json.loads("[" + text[first:stop] + "]"))
            if out is None:
                out = np.empty((count, a.shape[1]))
            out[at : at + len(a)] = a
            at += len(a)
            first = text.find("[", stop, last) if stop < last else last
            first = last if first < 0 else first
        if out is None or at != count:
            raise _Leave
        return out

    def floats(self, rows: list) -> np.ndarray:
        """Rows of numbers -> (rows, width) float64 of one width."""
        a = np.array(rows, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] == 0 or a.shape[1] != (self.width or a.shape[1]):
            raise _Leave
        self.width = a.shape[1]
        return a

    def block(self, a: np.ndarray, rollouts: int) -> None:
        self.blocks.append(a)
        self.first.append(self.first[-1] + rollouts)

    def stack(self) -> RolloutStack:
        self.flush()
        first = np.frombuffer(self.first, dtype=np.int64)
        if self.states is not None:
            if self.rollouts != len(self.states):
                raise _Leave
            return RolloutStack(self.blocks, self.states.bounds, first, self.width or 0, less=1)
        if self.bounds[-1] != sum(len(b) for b in self.blocks):
            raise _Leave
        bounds = np.frombuffer(self.bounds, dtype=np.int64)
        return RolloutStack(self.blocks, bounds, first, self.width or 0)


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
