"""Work that holds something scarce while it runs, counted per team and in all in
one API process: an upload being read (memory: :mod:`svrobs_lab.datasets.upload_slots`),
a job's results being streamed (a database connection, for as long as the client
takes to read them: :data:`StreamSlots`). At most ``per_team`` of one team and
``at_once`` in all; beyond either, :class:`~svrobs_lab.errors.RateLimited` (429,
Retry-After: the last holder's duration) before the work starts.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from .errors import RateLimited


class TeamSlots:
    """Counted slots per team and in all, for one process; ``what`` names what holds
    them in the refusal's message, ``settings`` the two settings of the bounds."""

    def __init__(self, *, per_team: int, at_once: int, what: str, settings: tuple[str, str]):
        self.per_team = per_team
        self.at_once = at_once
        self.what = what
        self.settings = settings
        self._lock = threading.Lock()
        self._teams: Counter[int] = Counter()
        self._last_seconds = 1.0

    def _busy(self, what: str, setting: str) -> RateLimited:
        retry = max(1, round(self._last_seconds))
        return RateLimited(f"{what}: retry in {retry} s ({setting})", retry_after=retry)

    def in_use(self, team_id: int | None = None) -> int:
        """Slots held by the team (None: by every team)."""
        with self._lock:
            return self._teams.total() if team_id is None else self._teams[team_id]

    def take(self, team_id: int) -> Callable[[], None]:
        """One of the team's slots -> the function that gives it back (once, however
        often it is called); RateLimited if none is free."""
        with self._lock:
            if self._teams[team_id] >= self.per_team:
                raise self._busy(
                    f"this team already has {self.per_team} {self.what}", self.settings[0]
                )
            if self._teams.total() >= self.at_once:
                raise self._busy(f"{self.at_once} {self.what} in all", self.settings[1])
            self._teams[team_id] += 1
        started, given = time.monotonic(), threading.Event()

        def release() -> None:
            with self._lock:
                if given.is_set():
                    return
                given.set()
                self._teams[team_id] -= 1
                if self._teams[team_id] <= 0:
                    del self._teams[team_id]
                self._last_seconds = time.monotonic() - started

        return release

    @contextmanager
    def hold(self, team_id: int) -> Iterator[None]:
        """One of the team's slots while the block runs; RateLimited if none is free."""
        release = self.take(team_id)
        try:
            yield
        finally:
            release()


def stream_slots(*, per_team: int, at_once: int) -> TeamSlots:
    """The slots of results streamed at once (CSV, JSON lines): each holds a database
    connection until its client has read the last row (SVROBS_STREAMS_PER_TEAM,
    SVROBS_STREAMS_AT_ONCE)."""
    return TeamSlots(
        per_team=per_team,
        at_once=at_once,
        what="results streams being sent",
        settings=("SVROBS_STREAMS_PER_TEAM", "SVROBS_STREAMS_AT_ONCE"),
    )
