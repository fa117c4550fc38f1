"""Per-cell notes: the reasons a record field is null (docs/spec.md#notes-why-a-field-is-null)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array


class Notes:
    """Per-cell reasons for null fields over the (R, E) grid, vectorised.

    ``add(mask, text)`` records one (text, cell mask) entry; a cell's notes
    are the texts of the entries that hold for it, in the order they were
    added, each text once, joined by "; " (None when there is none).
    """

    def __init__(self, shape: Iterable[int]) -> None:
        self.shape = tuple(shape)
        self._entries: list[tuple[str, Array]] = []
        self.tags: dict[str, int] = {}

    def add(self, mask: ArrayLike, text: str, tag: str | None = None) -> None:
        """``tag``: name the entry (kept even when its mask is empty) so that
        :meth:`replace` can change it later."""
        m = np.broadcast_to(np.asarray(mask, dtype=bool), self.shape)
        if tag is not None:
            self.tags[tag] = len(self._entries)
            self._entries.append((text, m))
        elif m.any():
            self._entries.append((text, m))

    def replace(self, tag: str, mask: ArrayLike, text: str) -> Notes:
        """A copy with the tagged entry's mask and text replaced (same position)."""
        new = Notes(self.shape)
        new._entries = list(self._entries)
        new.tags = dict(self.tags)
        new._entries[self.tags[tag]] = (
            text,
            np.broadcast_to(np.asarray(mask, dtype=bool), self.shape),
        )
        return new

    def embed(self, other: Notes, rows: Any) -> None:
        """Append the entries of ``other``, the notes of the rows ``rows`` of this grid."""
        for text, m in other._entries:
            full = np.zeros(self.shape, dtype=bool)
            full[rows] = m
            self._entries.append((text, full))

    def add_reasons(self, reasons: Any, prefix: str | None) -> None:
        """One entry per distinct reason of an object array (or a scalar)
        broadcasting to the grid; empty / None reasons are skipped."""
        r = np.broadcast_to(np.asarray(reasons, dtype=object), self.shape)
        for value in dict.fromkeys(v for v in r.ravel().tolist() if v):
            text = value if prefix is None else f"{prefix}: {value}"
            self.add(r == value, text)

    def strings(self) -> Array:
        """Object array (R, E) of the joined notes (None where there are none)."""
        out = np.full(self.shape, None, dtype=object)
        if not self._entries:
            return out
        words = []
        for w0 in range(0, len(self._entries), 62):
            code = np.zeros(self.shape, dtype=np.int64)
            for i, (_, m) in enumerate(self._entries[w0 : w0 + 62]):
                code |= m.astype(np.int64) << i
            words.append(code.reshape(-1))
        codes = np.stack(words, axis=1)
        uniq, inv = np.unique(codes, axis=0, return_inverse=True)
        texts: list[Any] = []
        for row in uniq.tolist():
            seen: list[str] = []
            for i, (t, _) in enumerate(self._entries):
                if (row[i // 62] >> (i % 62)) & 1 and t not in seen:
                    seen.append(t)
            texts.append("; ".join(seen) if seen else None)
        table = np.empty(len(texts), dtype=object)
        table[:] = texts
        return table[inv.reshape(-1)].reshape(self.shape)
