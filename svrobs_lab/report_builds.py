"""Report builds in one API process: one build per job at a time, a bounded number
per team, and the last report of each job kept until the job's progress changes
(docs/security.md#reports-of-running-jobs). A dataset job's validation computed on
request (:mod:`svrobs_lab.validation`) is such a build too, under its own key, and
counts against the same bounds.

:meth:`ReportBuilds.get` is given the job's key (its id and creation time: SQLite
gives the id of a deleted job to the next job made, which may be another team's) and
``version`` (its status, units done and cells done): a kept report of that job and
version is returned at once; else the request joins the job's build in progress (it
waits for that one build) or starts one.
A team already running ``per_team`` builds, or with ``waiters_per_team`` requests
waiting, is refused with :class:`~svrobs_lab.errors.RateLimited` (429, Retry-After:
the last build's duration). Nothing here touches the database: the caller reads
what it needs and closes its session before calling.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Hashable
from typing import Any, TypeVar

from .errors import RateLimited

log = logging.getLogger(__name__)

WAIT_SECONDS = 300.0  # a request waits at most this long for another's build
T = TypeVar("T")


class _Flight:
    def __init__(self, version: Hashable):
        self.version = version
        self.done = threading.Event()
        self.built = False
        self.result: Any = None  # what the build returned (a page, a validation)
        self.error: BaseException | None = None


class ReportBuilds:
    """Single-flight report builds with a per-team bound and a small kept set."""

    def __init__(self, *, per_team: int, waiters_per_team: int, keep: int = 16):
        self.per_team = per_team
        self.waiters_per_team = waiters_per_team
        self.keep = keep
        self._lock = threading.Lock()
        self._flights: dict[Hashable, _Flight] = {}
        self._building: Counter[int] = Counter()
        self._waiting: Counter[int] = Counter()
        self._kept: OrderedDict[Hashable, tuple[Hashable, Any]] = OrderedDict()
        self._last_seconds = 5.0
        self.builds = 0  # builds started (for tests and the bench)

    def retry_after(self) -> int:
        return max(1, round(self._last_seconds))

    def _busy(self, what: str) -> RateLimited:
        retry = self.retry_after()
        return RateLimited(
            f"{what}: retry in {retry} s (SVROBS_REPORT_BUILDS_PER_TEAM)", retry_after=retry
        )

    def kept(self, job: Hashable, version: Hashable) -> Any:
        """The kept report of the job keyed ``job`` if it was built at ``version``."""
        with self._lock:
            hit = self._kept.get(job)
            if hit is None or hit[0] != version:
                return None
            self._kept.move_to_end(job)
            return hit[1]

    def forget(self, job: Hashable) -> None:
        with self._lock:
            self._kept.pop(job, None)

    def get(self, job: Hashable, team_id: int, version: Hashable, build: Callable[[], T]) -> T:
        """The report of the job keyed ``job`` (its id and creation time, one job of one
        team) at ``version``: kept, another request's build in progress, or ``build()``
        run here (and kept)."""
        with self._lock:
            hit = self._kept.get(job)
            if hit is not None and hit[0] == version:
                self._kept.move_to_end(job)
                return hit[1]
            flight = self._flights.get(job)
            if flight is not None:
                if self._waiting[team_id] >= self.waiters_per_team:
                    raise self._busy("too many report requests of this team are waiting")
                self._waiting[team_id] += 1
                leader = False
            else:
                if self._building[team_id] >= self.per_team:
                    raise self._busy(
                        f"this team already builds {self.per_team} reports (or validations)"
                    )
                flight = self._flights[job] = _Flight(version)
                self._building[team_id] += 1
                self.builds += 1
                leader = True
        if not leader:
            return self._wait(flight, team_id)
        return self._lead(flight, job, team_id, build)

    def _wait(self, flight: _Flight, team_id: int) -> Any:
        try:
            finished = flight.done.wait(WAIT_SECONDS)
        finally:
            with self._lock:
                self._waiting[team_id] -= 1
        if not finished:
            raise self._busy("the report is still being built")
        if flight.error is not None:
            raise flight.error
        assert flight.built
        return flight.result

    def _lead(self, flight: _Flight, job: Hashable, team_id: int, build: Callable[[], T]) -> T:
        started = time.monotonic()
        log.info("building %s (team %s)", job, team_id)
        try:
            result = build()
            flight.result, flight.built = result, True
        except BaseException as exc:
            flight.error = exc
            raise
        finally:
            with self._lock:
                self._building[team_id] -= 1
                del self._flights[job]
                if flight.built:
                    self._last_seconds = time.monotonic() - started
                    self._kept[job] = (flight.version, flight.result)
                    self._kept.move_to_end(job)
                    while len(self._kept) > self.keep:
                        self._kept.popitem(last=False)
            flight.done.set()
        log.info("built %s in %.1f s", job, time.monotonic() - started)
        return result
