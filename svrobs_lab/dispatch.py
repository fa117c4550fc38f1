"""Dispatch: publishing a team's next work units within its fair share
(:func:`service.db.outbox.dispatch`), after a request's commit or a unit's end, and
the relay that re-publishes what was missed (docs/architecture.md#one-job).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from contextlib import contextmanager

from sqlalchemy.orm import Session

from service.config import Settings
from service.db import outbox

log = logging.getLogger(__name__)

SessionFactory = Callable[..., Session]  # factory(write: bool) -> Session
Publisher = Callable[[Sequence[int]], list[int]]


def outbox_policy(settings: Settings) -> dict:
    """The keyword arguments of :func:`service.db.outbox.dispatch` that ``settings``
    sets: the fair share's caps (``Settings.fair_share``) and the re-publishing delay
    (SVROBS_PUBLISH_RETRY_SECONDS)."""
    cap, shared_cap = settings.fair_share()
    return {
        "cap": cap,
        "shared_cap": shared_cap,
        "retry_seconds": settings.PUBLISH_RETRY_SECONDS,
    }


def dispatch_after_commit(
    settings: Settings,
    publisher: Publisher,
    session_factory: SessionFactory,
    team_id: int,
) -> None:
    """Send the team's next units to the broker (within its fair share under
    ``settings``: :func:`outbox_policy`) and mark them published; what fails is left to
    the relay."""

    @contextmanager
    def begin():
        session = session_factory(True)
        try:
            yield session
            session.commit()
        finally:
            session.close()

    try:
        outbox.dispatch(begin, publisher, team_id=team_id, **outbox_policy(settings))
    except Exception as exc:  # noqa: BLE001 - best effort after the response: the relay retries
        log.warning("publishing the units of team %s failed: %s", team_id, exc)


def dispatch_team_of_unit(settings: Settings, scope, publisher: Publisher, unit_id: int) -> None:
    """Publish the next units now that ``unit_id``'s pool process is free: of every
    team with units waiting, round-robin, each within its fair share under ``settings``
    (its own team's, and another's whose cap was one less while this team had work);
    ``scope()`` is a committing session context (:func:`service.db.session.session_scope`
    on the settings' database); ``unit_id`` is the unit that ended (any waiting team may
    take its slot). Raises what the DB or broker raise."""
    outbox.dispatch(scope, publisher, **outbox_policy(settings))


def relay(
    settings: Settings, scope, publisher: Publisher, *, lost_before, limit: int, batch: int
) -> int:
    """Publish units that need it, every team within its fair share under ``settings``,
    ``batch`` at a time up to ``limit``; units published before ``lost_before`` (the
    broker's epoch) or more than SVROBS_PUBLISH_RETRY_SECONDS ago are re-published.
    Returns how many were published."""
    policy = outbox_policy(settings)
    sent = 0
    while sent < limit:
        size = min(batch, limit - sent)
        n = outbox.dispatch(
            scope, publisher, republish=True, lost_before=lost_before, limit=size, **policy
        )
        sent += n
        if n < size:  # nothing more, or the broker took only part: next tick
            break
    return sent
