"""Uploads read at once in one API process (docs/datasets.md#limits): at most
``per_team`` of one team and ``at_once`` in all, each held from the first byte of
the body read until the dataset is stored or refused. A file can take several times
its size in memory while it is parsed, so beyond either bound the upload is refused
at once with :class:`~svrobs_lab.errors.RateLimited` (429, Retry-After: the last
upload's duration), before its body is read.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager

from ..errors import RateLimited


class UploadSlots:
    """Counted upload slots per team and in all, for one process."""

    def __init__(self, *, per_team: int, at_once: int):
        self.per_team = per_team
        self.at_once = at_once
        self._lock = threading.Lock()
        self._teams: Counter[int] = Counter()
        self._last_seconds = 1.0

    def _busy(self, what: str, setting: str) -> RateLimited:
        retry = max(1, round(self._last_seconds))
        return RateLimited(f"{what}: retry in {retry} s ({setting})", retry_after=retry)

    @contextmanager
    def hold(self, team_id: int) -> Iterator[None]:
        """One of the team's slots while the block runs; RateLimited if none is free."""
        with self._lock:
            if self._teams[team_id] >= self.per_team:
                raise self._busy(
                    f"this team already has {self.per_team} uploads being read",
                    "SVROBS_UPLOADS_PER_TEAM",
                )
            if self._teams.total() >= self.at_once:
                raise self._busy(f"{self.at_once} uploads are being read", "SVROBS_UPLOADS_AT_ONCE")
            self._teams[team_id] += 1
        started = time.monotonic()
        try:
            yield
        finally:
            with self._lock:
                self._teams[team_id] -= 1
                if self._teams[team_id] <= 0:
                    del self._teams[team_id]
                self._last_seconds = time.monotonic() - started
