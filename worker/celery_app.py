"""The Celery app every worker and beat process loads (``celery -A worker.celery_app``).

Celery itself is configured in one place, ``service.broker.make_celery``; this
module only adds the task modules, the consumer that drops task messages the worker
cannot run (:mod:`worker.message_guard`), the beat schedule (one ``svrobs.tick`` every
``SVROBS_TICK_SECONDS``; the integration tests use 1-2) and the process's logging
(:func:`service.logging_config.configure_logging`, instead of Celery's own).
"""

from __future__ import annotations

from celery import signals

from service.broker import make_celery
from service.config import get_settings
from service.logging_config import configure_logging
from worker import recovery, watchdog  # noqa: F401 (recovery: its signal handler)
from worker.message_guard import CONSUMER

settings = get_settings()


@signals.setup_logging.connect
def _setup_logging(**_kwargs) -> None:
    """Worker and beat: the service's logging replaces Celery's (its ``-l`` is unused)."""
    configure_logging(settings)


celery_app = make_celery(settings)
celery_app.conf.worker_consumer = CONSUMER
if watchdog.enabled(settings):
    celery_app.steps["consumer"].add(watchdog.ConsumerWatchdog)
celery_app.conf.include = list(celery_app.conf.include or ()) + ["worker.tasks"]
celery_app.conf.beat_schedule = {
    "svrobs-tick": {
        "task": "svrobs.tick",
        "schedule": settings.TICK_SECONDS,
        # if a tick is ever sent to the broker rather than run by worker.beat.TickScheduler,
        # a stale one is dropped instead of piling up behind long units
        "options": {"expires": max(1.0, settings.TICK_SECONDS)},
    },
}
app = celery_app  # what `celery -A worker.celery_app` also finds

# register the tasks now (and not only on worker start) so that beat and the
# tests see them too
import worker.tasks  # noqa: F401, E402
