"""Celery configuration and publishing (filesystem broker; an unreachable Redis)."""

from __future__ import annotations

import os
import ssl

import pytest

from service.broker import (
    RUN_UNIT_TASK,
    BrokerPublisher,
    check_broker,
    make_celery,
    publish_units,
)
from service.config import Settings


def test_make_celery_settings(tmp_path):
    app = make_celery(
        Settings(BROKER_URL="filesystem://", BROKER_DIR=str(tmp_path / "b"), TASK_TIME_LIMIT=100)
    )
    c = app.conf
    assert c.task_serializer == "json" and c.result_serializer == "json"
    assert list(c.accept_content) == ["json"]
    assert c.task_acks_late and c.task_reject_on_worker_lost
    assert c.worker_prefetch_multiplier == 1 and c.task_time_limit == 100
    assert c.task_ignore_result
    opts = c.broker_transport_options
    for key in ("data_folder_in", "data_folder_out", "processed_folder"):
        assert os.path.isdir(opts[key])
    redis = make_celery(Settings(BROKER_URL="redis://127.0.0.1:6379/0", TASK_TIME_LIMIT=100))
    assert redis.conf.broker_transport_options["visibility_timeout"] > 100


@pytest.mark.parametrize(
    "url, checked",
    [
        ("rediss://broker.example:6380/0", ssl.CERT_REQUIRED),
        ("rediss://broker.example:6380/0?ssl_cert_reqs=required", ssl.CERT_REQUIRED),
        ("rediss://broker.example:6380/0?ssl_cert_reqs=none", ssl.CERT_NONE),
        ("redis://broker.example:6379/0", None),
    ],
)
def test_redis_broker_connection_and_tls(url, checked):
    """A Redis URL gets the transport that sets aside bad items; a rediss URL is TLS
    with the certificate checked unless the URL says otherwise."""
    app = make_celery(Settings(BROKER_URL=url))
    conn = app.connection_for_write()
    assert conn.transport_cls == "service.redis_broker:Transport"
    assert (conn.ssl or {}).get("ssl_cert_reqs") == checked
    conn.release()


def test_publish_to_filesystem_broker(tmp_path):
    app = make_celery(Settings(BROKER_URL="filesystem://", BROKER_DIR=str(tmp_path / "b")))
    check_broker(app)
    assert publish_units(app, [3, 4, 5]) == [3, 4, 5]
    folder = app.conf.broker_transport_options["data_folder_in"]
    files = os.listdir(folder)
    assert len(files) == 3
    import json

    msg = json.loads(open(os.path.join(folder, files[0])).read())
    assert msg["headers"]["task"] == RUN_UNIT_TASK
    assert msg["content-type"] == "application/json"


def test_broker_publisher_makes_one_app_on_first_use(tmp_path):
    asked = []

    def settings_of():
        asked.append(1)
        return Settings(BROKER_URL="filesystem://", BROKER_DIR=str(tmp_path / "b"))

    publisher = BrokerPublisher(settings_of)
    assert asked == []  # nothing made before the first publish
    assert publisher([7, 8]) == [7, 8]
    app = publisher.get_celery()
    assert publisher.get_celery() is app and len(asked) == 1
    assert len(os.listdir(app.conf.broker_transport_options["data_folder_in"])) == 2


@pytest.mark.timeout(60)  # the bound is the broker timeout: without it this would hang
def test_publish_with_broker_down_returns_quickly():
    app = make_celery(Settings(BROKER_URL="redis://127.0.0.1:1/0", BROKER_TIMEOUT=0.5))
    assert publish_units(app, [1, 2]) == []


def _drain_polls(tmp_path, monkeypatch, timeout: float) -> int:
    """How many times a consumer of an empty queue polls it in ``drain_events(timeout)``."""
    from kombu import Exchange, Queue

    from service import file_broker

    polls = []
    real_get = file_broker.Channel._get

    def counted(self, queue):
        polls.append(queue)
        return real_get(self, queue)

    monkeypatch.setattr(file_broker.Channel, "_get", counted)
    app = make_celery(
        Settings(BROKER_URL="filesystem://", BROKER_DIR=str(tmp_path), BROKER_POLL_SECONDS=0.02)
    )
    queue = Queue("t", Exchange("t", type="direct"), routing_key="t")
    with app.connection_for_write() as conn, conn.Consumer(queue, callbacks=[]):
        with pytest.raises(TimeoutError):
            conn.drain_events(timeout=timeout)
    return len(polls)


@pytest.mark.timeout(60)
def test_a_stopping_worker_stops_waiting_for_messages_at_the_next_poll(tmp_path, monkeypatch):
    """Celery's loop for the filesystem broker waits 2 s per call: a worker told to stop
    gives up after one polling interval instead of the whole wait."""
    from celery.worker import state

    # the whole wait, polled once per interval of 0.02 s (a sleep is never shorter)
    assert 4 <= _drain_polls(tmp_path / "a", monkeypatch, 0.3) <= 1 + 15
    monkeypatch.setattr(state, "should_stop", 0)  # what a worker's SIGTERM handler sets
    assert _drain_polls(tmp_path / "b", monkeypatch, 50.0) <= 3  # not 2,500 polls


@pytest.mark.skipif(
    not os.environ.get("SVROBS_TEST_BROKER_URL"), reason="SVROBS_TEST_BROKER_URL not set"
)
def test_redis_synchronous_get_sets_aside_items_that_are_not_messages(caplog):
    """``basic_get`` (kombu's synchronous ``_get``) on a real Redis: raw items ahead of a
    message are logged and kept on the bad list, and the message behind them is
    returned; kombu's own transport raises on the first of them."""
    import kombu
    import redis as redis_py

    from service.redis_broker import BAD_LIST

    # database 15 of the test server: the integration stacks flush theirs
    url = os.environ["SVROBS_TEST_BROKER_URL"].rsplit("/", 1)[0] + "/15"
    r = redis_py.Redis.from_url(url)
    queue = f"svrobs-test-get-{os.getpid()}"
    raw = [b"not json", b"\xff\xfe", b'{"properties": 1}']
    r.delete(queue, BAD_LIST)
    try:
        with kombu.Connection(url, transport="service.redis_broker:Transport") as conn:
            q = conn.SimpleQueue(queue)
            r.lpush(queue, *raw)  # the oldest first: RPOP takes them before the message
            q.put({"ok": 1})
            r.rpush(queue, r.lpop(queue))  # the message behind the raw items
            with caplog.at_level("ERROR", logger="service.redis_broker"):
                msg = q.get(block=False)
            assert msg.payload == {"ok": 1}
            msg.ack()
            with pytest.raises(q.Empty):
                q.get(block=False)
            q.close()
        assert sorted(r.lrange(BAD_LIST, 0, -1)) == sorted(raw)
        assert sum("is not a message" in m for m in caplog.messages) == len(raw)
        r.rpush(queue, b"not json")  # kombu's transport: the raw item is an error
        with kombu.Connection(url) as conn:
            plain = conn.SimpleQueue(queue)
            with pytest.raises(ValueError):
                plain.get(block=False)
            plain.close()
    finally:
        r.delete(queue, BAD_LIST)
        r.close()
