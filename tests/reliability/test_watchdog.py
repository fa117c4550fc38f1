"""The consumer watchdog (worker.watchdog): its decision against an independent
restatement, and its queue sample against what was published, on the filesystem
broker and on a real Redis. The end-to-end case (a stalled worker reconnects and
the sweep completes) is tests/faults test_stalled_consumer_reconnects."""

from __future__ import annotations

import random
from types import SimpleNamespace

import pytest

from service.broker import make_celery, publish_units
from service.config import Settings
from tests.integration.servers import REDIS_SERVER, PrivateRedis
from worker.watchdog import StallDetector, ready_messages


def _oracle(samples: list[tuple[int, int, int]], start: int, checks: int) -> list[bool]:
    """Fires after `checks` stuck samples in a row (waiting, free, no new message);
    the count starts again after it fires."""
    out, run, last = [], 0, start
    for ready, free, received in samples:
        stuck = ready > 0 and free > 0 and received == last
        last = received
        run = run + 1 if stuck else 0
        out.append(run >= checks)
        if run >= checks:
            run, last = 0, received
    return out


def test_stall_detector_fires_only_after_checks_stuck_samples():
    d = StallDetector(checks=3, received=5)
    assert [d.observe(4, 1, 5) for _ in range(3)] == [False, False, True]
    d = StallDetector(checks=3, received=5)
    assert not any(
        d.observe(*s)
        for s in [
            (4, 1, 5),
            (4, 1, 5),
            (4, 1, 6),
            (4, 1, 6),
            (0, 1, 6),
            (4, 0, 6),
            (4, 1, 6),
            (4, 1, 6),
        ]
    )


@pytest.mark.parametrize("seed", range(5))
def test_stall_detector_matches_oracle_on_random_samples(seed):
    rnd = random.Random(seed)
    samples, received = [], 0
    for _ in range(400):
        received += rnd.random() < 0.3
        samples.append((rnd.choice([0, 0, 3]), rnd.choice([0, 1, 2]), received))
    d = StallDetector(checks=3, received=0)
    got = []
    for s in samples:
        fired = d.observe(*s)
        got.append(fired)
        if fired:  # the worker reconnects; ConsumerWatchdog.start begins a new count
            d = StallDetector(received=s[2])
    assert got == _oracle(samples, 0, 3)
    assert any(got) and not all(got)


def _consumer(app):
    queues = list(app.amqp.queues.values())
    return SimpleNamespace(
        connection=app.connection_for_read(), app=app, task_consumer=SimpleNamespace(queues=queues)
    )


def test_ready_messages_filesystem(tmp_path):
    app = make_celery(Settings(BROKER_URL="filesystem://", BROKER_DIR=str(tmp_path / "b")))
    c = _consumer(app)
    assert ready_messages(c) == 0
    assert publish_units(app, [1, 2, 3]) == [1, 2, 3]
    assert ready_messages(c) == 3


@pytest.mark.skipif(REDIS_SERVER is None, reason="redis-server not installed")
def test_ready_messages_redis(tmp_path):
    redis = PrivateRedis(tmp_path / "redis")
    redis.start()
    try:
        app = make_celery(Settings(BROKER_URL=redis.url))
        c = _consumer(app)
        assert ready_messages(c) == 0
        assert publish_units(app, range(1, 8)) == list(range(1, 8))
        assert ready_messages(c) == 7
        c.connection.release()
    finally:
        redis.stop()


def test_enabled_only_for_redis_brokers():
    from worker.watchdog import enabled

    assert enabled(Settings(BROKER_URL="redis://127.0.0.1:6379/0"))
    assert not enabled(Settings(BROKER_URL="redis://127.0.0.1:6379/0", WORKER_WATCHDOG_SECONDS=0))
    assert not enabled(Settings(BROKER_URL="filesystem://"))


def test_capacity_needs_a_free_process_and_room_in_the_window():
    from worker.watchdog import capacity

    def consumer(size, room):
        qos = SimpleNamespace(can_consume=lambda: room)
        return SimpleNamespace(
            pool=SimpleNamespace(num_processes=size),
            task_consumer=SimpleNamespace(channel=SimpleNamespace(qos=qos)),
        )

    assert capacity(consumer(2, True)) == 2  # nothing reserved in this test process
    assert capacity(consumer(2, False)) == 0
