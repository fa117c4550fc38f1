"""Dispatch: publishing a team's next work units within its fair share
(:func:`service.db.outbox.dispatch`), after a request's commit or a unit's end, and
the relay that re-publishes what was missed (docs/architecture.md#one-job).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from contextlib import contextmanager

from sqlalchemy.orm import Session

from service.db import outbox

log = logging.getLogger(__name__)

SessionFactory = Callable[..., Session]  # factory(write: bool) -> Session
Publisher = Callable[[Sequence[int]], list[int]]


def dispatch_after_commit(
    publisher: Publisher,
    session_factory: SessionFactory,
    team_id: int,
    cap: int,
    shared_cap: int | None = None,
) -> None:
    """Send the team's next units to the broker (within its fair share: ``cap``, or
    ``shared_cap`` while another team has work; ``Settings.fair_share``) and mark them
    published; what fails is left to the relay."""

    @contextmanager
    def begin():
        session = session_factory(True)
        try:
            yield session
            session.commit()
        finally:
            session.close()

    try:
        outbox.dispatch(begin, publisher, team_id=team_id, cap=cap, shared_cap=shared_cap)
    except Exception as exc:  # noqa: BLE001 - best effort after the response: the relay retries
        log.warning("publishing the units of team %s failed: %s", team_id, exc)


def dispatch_team_of_unit(scope, publisher: Publisher, unit_id: int) -> None:
    """Publish the next units now that ``unit_id``'s pool process is free: of every
    team with units waiting, round-robin, each within its fair share (its own team's,
    and another's whose cap was one less while this team had work); ``scope`` is
    :func:`service.db.session.session_scope`; ``unit_id`` is the unit that ended (any
    waiting team may take its slot). Raises what the DB or broker raise."""
    outbox.dispatch(scope, publisher)


def relay(scope, publisher: Publisher, *, lost_before, limit: int, batch: int) -> int:
    """Publish units that need it, every team within its fair share, ``batch`` at a
    time up to ``limit``; units published before ``lost_before`` (the broker's epoch)
    are re-published. Returns how many were published."""
    sent = 0
    while sent < limit:
        size = min(batch, limit - sent)
        n = outbox.dispatch(scope, publisher, republish=True, lost_before=lost_before, limit=size)
        sent += n
        if n < size:  # nothing more, or the broker took only part: next tick
            break
    return sent
