"""The Celery app every worker and beat process loads (``celery -A worker.celery_app``).

Celery itself is configured in one place, ``service.broker.make_celery``; this
module only adds the task modules and the beat schedule: one ``svrobs.tick``
every ``SVROBS_TICK_SECONDS`` (60 by default; the integration tests use 1-2).
"""

from __future__ import annotations

import os

import worker
from service.broker import make_celery
from service.config import get_settings
from worker import watchdog

settings = get_settings()


def tick_seconds() -> float:
    value = getattr(settings, "TICK_SECONDS", None) or os.environ.get("SVROBS_TICK_SECONDS")
    return float(value) if value else 60.0


celery_app = make_celery(settings)
if watchdog.enabled(settings):
    celery_app.steps["consumer"].add(watchdog.ConsumerWatchdog)
celery_app.conf.include = list(celery_app.conf.include or ()) + ["worker.tasks"]
celery_app.conf.beat_schedule = {
    "svrobs-tick": {
        "task": "svrobs.tick",
        "schedule": tick_seconds(),
        # if a tick is ever sent to the broker rather than run by worker.beat.TickScheduler,
        # a stale one is dropped instead of piling up behind long units
        "options": {"expires": max(1.0, tick_seconds())},
    },
}
app = celery_app  # what `celery -A worker.celery_app` also finds

# register the tasks now (and not only on worker start) so that beat and the
# tests see them too
import worker.tasks  # noqa: F401
