"""A worker that starts takes back the units its node name left running.

A worker stopped or killed mid-unit (``svrobs serve`` stopped with Ctrl-C, a pool
SIGKILLed, a container restarted) leaves its units ``running`` with a lease of up to
``SVROBS_UNIT_LEASE_SECONDS``, and their messages are gone (the embedded broker
deletes a message when it is claimed; Redis holds it unacknowledged until its
visibility timeout). When a worker of the same node name starts, before it takes a
message, it ends those units' leases (:func:`service.db.units.expire_leases_of`) and
runs the relay (:func:`worker.tick.relay`), which re-publishes them at once: the job
goes on within seconds, not after the lease (docs/deploy.md#scaling).
"""

from __future__ import annotations

import logging

from celery import signals

log = logging.getLogger(__name__)


@signals.worker_ready.connect
def take_back_units(sender=None, **_kwargs) -> None:
    """On ``worker_ready`` (sent before the consumer's loop takes a message)."""
    from service.db import units
    from worker.tick import relay, session_scope

    name = getattr(sender, "hostname", None)
    if not name:
        return
    try:
        with session_scope() as s:
            ids = units.expire_leases_of(s, name)
        if ids:
            log.warning(
                "%s: %d unit(s) this node left running (stopped or killed mid-unit): %s; "
                "re-published",
                name,
                len(ids),
                ", ".join(map(str, ids)),
            )
            relay(getattr(sender, "app", None))
    except Exception as exc:  # noqa: BLE001 - the tick's relay does it within the lease
        log.warning("%s: could not take back the units it left running: %s", name, exc)
