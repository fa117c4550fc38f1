"""The tick: due schedules -> jobs, then the outbox relay.

``run_tick`` is what beat runs every TICK_SECONDS (in the beat process itself:
see :mod:`worker.beat`); it is safe to run from any number of processes at
once:

* ``schedules.create_due_schedule_jobs`` is keyed on (schedule, due time), so a
  doubled or restarted beat never creates a sweep twice;
* the relay publishes work units that were committed but never published
  (the API's publish failed, e.g. the broker was down, or the team had its
  fair share of units in flight) or whose lease ran out (the worker died and
  the broker did not redeliver), marking them first under the teams' locks.
  Publishing twice is harmless: ``units.start_unit`` lets one delivery run a
  unit and the other skip it, and results are upserted on the cell key.
"""

from __future__ import annotations

import logging
from datetime import UTC, datetime

log = logging.getLogger(__name__)

RELAY_BATCH = 500
RELAY_MAX_PER_TICK = 20_000


def create_due_jobs(now: datetime | None = None) -> list[int]:
    from service.db import schedules
    from service.db.session import session_scope

    now = now or datetime.now(UTC)
    with session_scope() as s:
        jobs = schedules.create_due_schedule_jobs(s, now)
        ids = [getattr(j, "id", j) for j in jobs or ()]
    if ids:
        log.info("tick: created jobs %s for due schedules", ids)
    return ids


def relay(celery=None, limit: int = RELAY_MAX_PER_TICK) -> int:
    """Publish units that need it, every team within its fair share
    (:func:`service.db.outbox.dispatch`); returns how many were published.

    Units published before the broker's current data began (``broker_epoch``: a
    Redis restarted without persistence lost them) are re-published at once.
    """
    from service.broker import broker_epoch, publish_units
    from service.db import outbox
    from service.db.session import session_scope

    if celery is None:
        from worker.celery_app import celery_app as celery
    epoch = broker_epoch(celery)  # raises if the broker is unreachable: retried next tick
    sent = 0
    while sent < limit:
        batch = min(RELAY_BATCH, limit - sent)
        n = outbox.dispatch(
            session_scope,
            lambda ids: publish_units(celery, ids),
            republish=True,
            lost_before=epoch,
            limit=batch,
        )
        sent += n
        if n < batch:  # nothing more, or the broker took only part: next tick
            break
    if sent:
        log.info("tick: relayed %d work units", sent)
    return sent


def run_tick(now: datetime | None = None, celery=None) -> dict:
    """One tick. Each half is independent: a failing relay never stops schedules."""
    out: dict = {"created": [], "relayed": 0, "errors": []}
    try:
        out["created"] = create_due_jobs(now)
    except Exception as exc:
        log.exception("tick: creating scheduled jobs failed")
        out["errors"].append(f"schedules: {type(exc).__name__}: {exc}")
    try:
        out["relayed"] = relay(celery)
    except Exception as exc:  # noqa: BLE001
        log.warning("tick: relay failed (%s: %s); will retry next tick", type(exc).__name__, exc)
        out["errors"].append(f"relay: {type(exc).__name__}: {exc}")
    return out
