"""Beat's scheduler: runs the ``svrobs.tick`` entry in the beat process itself.

A tick sent through the broker would wait behind long work units (one worker,
prefetch 1), so schedules would fall due late and the relay would stall
exactly when it is needed. The tick is short and idempotent, so beat (exactly
one per deployment; a doubled one is harmless, see :mod:`worker.tick`) runs it
in process; every other entry is sent to the broker as usual.

    celery -A worker.celery_app beat -S worker.beat:TickScheduler -s var/celerybeat-schedule
"""

from __future__ import annotations

import logging

from celery.beat import PersistentScheduler

log = logging.getLogger(__name__)
LOCAL_TASKS = {"svrobs.tick"}


class TickScheduler(PersistentScheduler):
    def setup_schedule(self):
        """The schedule, and beat's report thread from the start (not from the first
        tick, a whole ``TICK_SECONDS`` later): reports of jobs that finish meanwhile
        are stored before they are asked for."""
        super().setup_schedule()
        from worker.tick import start_report_builds

        start_report_builds()

    def apply_entry(self, entry, producer=None):
        if entry.task not in LOCAL_TASKS:
            return super().apply_entry(entry, producer=producer)
        from worker.tick import run_tick

        try:
            out = run_tick(celery=self.app)
        except Exception:
            log.exception("tick failed")
            return None
        if any(out.get(k) for k in ("created", "relayed", "pruned", "errors")):
            log.info("tick: %s", out)
        return None
