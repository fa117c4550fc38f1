"""Consumer watchdog: a worker whose consumer stopped taking messages reconnects.

After a broker restart a Celery worker can come back connected but no longer
consuming (celery/celery#8091, #9054, kombu#2007: fixed in kombu 5.4, but it is
the failure that loses a night's sweep, so the worker checks for it itself).
Every ``SVROBS_WORKER_WATCHDOG_SECONDS`` the consumer's event loop looks at three
numbers: messages ready in the worker's queues, free pool processes, and task
messages received since the last look. Messages waiting, a free process and
nothing received, :data:`STALLED_CHECKS` times in a row, is a stalled consumer:
the watchdog raises a connection error inside the event loop, and the worker
reconnects exactly as after a lost connection (running units keep running).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

from celery import bootsteps, signals
from celery.worker import state

log = logging.getLogger(__name__)

STALLED_CHECKS = 3
_received = [0]  # task messages this process received (the consumer runs in one thread)


@signals.task_received.connect
def _count_received(**_kwargs) -> None:
    _received[0] += 1


class ConsumerStalled(ConnectionError):
    """Raised in the event loop: one of the transport's connection errors, so the
    consumer takes its reconnect path."""


@dataclass
class StallDetector:
    """The decision, apart from Celery: :meth:`observe` one sample per check."""

    checks: int = STALLED_CHECKS
    received: int = 0
    stalled: int = 0

    def observe(self, ready: int, free: int, received: int) -> bool:
        """True when the consumer has been stalled for ``checks`` samples running."""
        stuck = ready > 0 and free > 0 and received == self.received
        self.received = received
        self.stalled = self.stalled + 1 if stuck else 0
        return self.stalled >= self.checks


def ready_messages(consumer) -> int:
    """Messages waiting in the queues this worker consumes from (a passive declare)."""
    conn = consumer.connection
    names = list(consumer.app.amqp.queues.consume_from or consumer.app.amqp.queues)
    total = 0
    for name in names:
        try:
            total += conn.default_channel.queue_declare(queue=name, passive=True).message_count
        except conn.channel_errors:  # not declared on this broker (yet): nothing waits
            continue
    return total


def free_processes(consumer) -> int:
    """Pool processes with no request: those reserved since the last (re)connection
    and those still running from before it (a reconnect clears the former only)."""
    size = getattr(consumer.pool, "num_processes", None) or consumer.controller.concurrency
    busy = set(state.reserved_requests) | set(state.active_requests)
    return max(0, int(size) - len(busy))


class ConsumerWatchdog(bootsteps.StartStopStep):
    """Consumer bootstep: a repeating check on the event loop's timer, registered
    again on each (re)connection."""

    requires = ("celery.worker.consumer.tasks:Tasks",)

    def __init__(self, consumer, **kwargs):
        super().__init__(consumer, **kwargs)
        self.interval = float(kwargs.get("interval") or _interval())
        self.entry = None
        self.detector = StallDetector()

    def start(self, consumer) -> None:
        self.detector = StallDetector(received=_received[0])
        self.entry = consumer.timer.call_repeatedly(self.interval, self.check, (consumer,))

    def stop(self, consumer) -> None:
        if self.entry is not None:
            self.entry.cancel()
            self.entry = None

    shutdown = stop

    def check(self, consumer) -> None:
        _test_stall_hook(consumer)
        try:
            ready, free = ready_messages(consumer), free_processes(consumer)
        except Exception as exc:  # noqa: BLE001 - the event loop reports a dead connection
            log.debug("watchdog: no sample (%s)", exc)
            return
        if self.detector.observe(ready, free, _received[0]):
            log.warning("watchdog: %d messages waiting and %d free pool processes, nothing "
                        "received for %d checks %g s apart: reconnecting", ready, free,
                        self.detector.checks, self.interval)
            self.detector = StallDetector(received=_received[0])
            raise ConsumerStalled("consumer stalled: reconnecting")


def _interval() -> float:
    from service.config import get_settings

    return float(get_settings().WORKER_WATCHDOG_SECONDS)


_stalled_once = [False]


def _test_stall_hook(consumer) -> None:
    """TEST-ONLY fault injection, off by default: with ``SVROBS_TEST_STALL_CONSUMER=1``
    the consumer stops consuming (``basic_cancel``, connection kept) once, after its
    first task message: the stalled-but-connected state the watchdog must undo."""
    if _stalled_once[0] or os.environ.get("SVROBS_TEST_STALL_CONSUMER") != "1":
        return
    if _received[0] >= 1 and consumer.task_consumer is not None:
        _stalled_once[0] = True
        log.warning("TEST: consumer cancelled (SVROBS_TEST_STALL_CONSUMER)")
        consumer.task_consumer.cancel()
