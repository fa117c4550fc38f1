"""Settings: typed fields from SVROBS_* variables, URLs checked at start-up; logging."""

from __future__ import annotations

import logging

import pytest
from pydantic import ValidationError

from service.config import BROKER_SCHEMES, Settings
from service.logging_config import configure_logging


@pytest.mark.parametrize(
    "url", ["not a url", "", "postgresql+psycopg://u@h:notaport/db", "://nohost"]
)
def test_malformed_database_url_is_rejected_naming_the_variable(monkeypatch, url):
    monkeypatch.setenv("SVROBS_DATABASE_URL", url)
    with pytest.raises(ValidationError) as e:
        Settings()
    assert "SVROBS_DATABASE_URL is not a database URL" in str(e.value)
    assert "Traceback" not in str(e.value)


@pytest.mark.parametrize(
    "url", ["redis//127.0.0.1:6379/0", "http://127.0.0.1:6379", "127.0.0.1:6379", "filesystem"]
)
def test_malformed_broker_url_is_rejected_naming_the_variable(monkeypatch, url):
    monkeypatch.setenv("SVROBS_BROKER_URL", url)
    with pytest.raises(ValidationError) as e:
        Settings()
    msg = str(e.value)
    assert "SVROBS_BROKER_URL is not a broker URL" in msg
    assert all(scheme in msg for scheme in BROKER_SCHEMES)


@pytest.mark.parametrize(
    "url",
    ["filesystem://", "memory://", "redis://127.0.0.1:6379/3", "rediss://h:6380/0", "amqp://h//"],
)
def test_broker_urls_in_use_are_accepted(url):
    assert Settings(BROKER_URL=url).BROKER_URL == url


def test_database_urls_in_use_are_accepted():
    for url in ("sqlite:///./var/svrobs.db", "sqlite://", "postgresql+psycopg://postgres@h:5432/x"):
        assert Settings(DATABASE_URL=url).DATABASE_URL == url


def test_every_setting_is_a_typed_field_read_from_the_environment(monkeypatch):
    monkeypatch.setenv("SVROBS_TICK_SECONDS", "1.5")
    monkeypatch.setenv("SVROBS_VAR_DIR", "/tmp/somewhere")
    monkeypatch.setenv("SVROBS_LOG_LEVEL", "debug")
    monkeypatch.setenv("SVROBS_TEST_CRASH_UNIT", "12")
    monkeypatch.setenv("SVROBS_TEST_STALL_CONSUMER", "1")
    s = Settings()
    assert (s.TICK_SECONDS, s.VAR_DIR, s.LOG_LEVEL) == (1.5, "/tmp/somewhere", "DEBUG")
    assert s.TEST_CRASH_UNIT == 12 and s.TEST_STALL_CONSUMER is True
    for bad in ("soon", "0", "-1"):  # a tick (and the report poll it bounds) must wait
        monkeypatch.setenv("SVROBS_TICK_SECONDS", bad)
        with pytest.raises(ValidationError, match="TICK_SECONDS"):
            Settings()
    monkeypatch.setenv("SVROBS_TICK_SECONDS", "2")
    monkeypatch.setenv("SVROBS_LOG_LEVEL", "loud")
    with pytest.raises(ValidationError, match="LOG_LEVEL"):
        Settings()


def test_defaults(monkeypatch):
    for var in ("SVROBS_VAR_DIR", "SVROBS_MAX_UNIT_ATTEMPTS"):
        monkeypatch.delenv(var, raising=False)
    s = Settings()
    assert s.VAR_DIR == "./var" and s.MAX_UNIT_ATTEMPTS == 5


def test_configure_logging_once_with_the_level_and_format(monkeypatch):
    root = logging.getLogger()
    monkeypatch.setattr(root, "handlers", [])
    monkeypatch.setattr(root, "level", root.level)
    configure_logging(Settings(LOG_LEVEL="WARNING"))
    configure_logging(Settings(LOG_LEVEL="DEBUG"))  # again: only the level changes
    assert len(root.handlers) == 1 and root.level == logging.DEBUG
    record = logging.LogRecord("service.db.jobs", logging.INFO, __file__, 1, "hello", None, None)
    line = root.handlers[0].format(record)
    assert line.endswith(" INFO service.db.jobs: hello") and line[:4].isdigit()
