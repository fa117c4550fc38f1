"""Celery configuration and publishing (filesystem broker; an unreachable Redis)."""

from __future__ import annotations

import os

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
