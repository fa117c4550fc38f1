"""Sizes of a list of rollouts ``X[i]`` (T_i + 1, n) with inputs ``U[i]`` (T_i, m)
(docs/datasets.md#the-data-model), for the classes that hold such lists."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any


class RolloutLists:
    """``n``, ``m`` and ``rollouts`` of the attributes ``X`` and ``U`` (sequences of
    2-D arrays, at least one rollout)."""

    __slots__ = ()
    X: Sequence[Any]
    U: Sequence[Any]

    @property
    def n(self) -> int:
        n: int = self.X[0].shape[1]
        return n

    @property
    def m(self) -> int:
        m: int = self.U[0].shape[1]
        return m

    @property
    def rollouts(self) -> int:
        return len(self.X)
