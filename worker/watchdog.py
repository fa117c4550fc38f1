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
"Free" also needs room in the channel's prefetch window, and the broker is asked
for its queue length only when everything else already looks stuck. Redis only:
the filesystem transport has no event loop (its worker polls) and no such failure.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from celery import bootsteps, signals
from celery.worker import state

log = logging.getLogger(__name__)

STALLED_CHECKS = 3
_received = [0]  # task messages this process received (the consumer runs in one thread)


@signals.task_received.connect
@signals.task_rejected.connect
@signals.task_unknown.connect
@signals.task_revoked.connect
def _count_received(**_kwargs) -> None:
    """Every message the consumer took: tasks, and those it dropped (unknown,
    undecodable, revoked or expired)."""
    _received[0] += 1


def enabled(settings) -> bool:
    return settings.WORKER_WATCHDOG_SECONDS > 0 and settings.BROKER_URL.startswith(
        ("redis:", "rediss:")
    )


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
    names = [q.name for q in getattr(consumer.task_consumer, "queues", None) or ()]
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


def window_open(consumer) -> bool:
    """Room in the task channel's prefetch window (acks_late: unacked messages count)."""
    qos = getattr(getattr(consumer.task_consumer, "channel", None), "qos", None)
    can_consume = getattr(qos, "can_consume", None)
    return bool(can_consume()) if can_consume is not None else True


def capacity(consumer) -> int:
    """Messages this consumer could take now: free processes, if the window has room."""
    return free_processes(consumer) if window_open(consumer) else 0


class ConsumerWatchdog(bootsteps.StartStopStep):
    """Consumer bootstep: a repeating check on the event loop's timer, registered
    again on each (re)connection."""

    requires = ("celery.worker.consumer.tasks:Tasks",)

    def __init__(self, consumer, **kwargs):
        from service.config import get_settings

        super().__init__(consumer, **kwargs)
        settings = get_settings()
        self.interval = float(settings.WORKER_WATCHDOG_SECONDS)
        self.test_stall = settings.TEST_STALL_CONSUMER
        self.entry = None
        self.detector = StallDetector()

    def start(self, consumer) -> None:
        """On each (re)connection: a fresh count and a fresh timer entry."""
        if getattr(consumer, "hub", None) is None:  # no event loop to raise into
            return
        self.detector = StallDetector(received=_received[0])
        self.entry = consumer.timer.call_repeatedly(self.interval, self.check, (consumer,))

    def stop(self, consumer) -> None:
        if self.entry is not None:
            self.entry.cancel()
            self.entry = None

    shutdown = stop

    def check(self, consumer) -> None:
        if self.test_stall:
            _test_stall_hook(consumer)
        received, free, ready = _received[0], capacity(consumer), 0
        if free and received == self.detector.received:  # only then ask the broker
            try:
                ready = ready_messages(consumer)
            except Exception as exc:  # noqa: BLE001 - the event loop reports a dead connection
                log.info("watchdog: no queue length (%s: %s)", type(exc).__name__, exc)
                return
        if self.detector.observe(ready, free, received):
            log.warning(
                "watchdog: %d messages waiting and %d free pool processes, nothing "
                "received for %d checks %g s apart: reconnecting",
                ready,
                free,
                self.detector.checks,
                self.interval,
            )
            raise ConsumerStalled("consumer stalled: reconnecting")


_stalled_once = [False]


def _test_stall_hook(consumer) -> None:
    """TEST-ONLY fault injection, off by default: with ``SVROBS_TEST_STALL_CONSUMER=1``
    the consumer stops consuming (``basic_cancel``, connection kept) once, after its
    first task message: the stalled-but-connected state the watchdog must undo."""
    if _stalled_once[0]:
        return
    if _received[0] >= 1 and consumer.task_consumer is not None:
        _stalled_once[0] = True
        log.warning("TEST: consumer cancelled (SVROBS_TEST_STALL_CONSUMER)")
        consumer.task_consumer.cancel()
