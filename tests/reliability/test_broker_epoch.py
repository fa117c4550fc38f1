"""Two failures the fault tests (tests/faults) exercise, checked in process.

A unit that keeps killing its worker fails after K attempts, and the job says
what killed the worker: the worker's main process records it on the unit
(``units.note_unit_error``).

A Redis restarted without persistence has lost its queue. Waiting for
PUBLISH_RETRY_SECONDS (10 min by default) after the units' last publication
would stall a sweep that long, so the relay keeps a marker key in the broker's
Redis database (``broker_epoch``): the marker and the queue live and die
together, and units published before the marker's time are re-published at the
next tick.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest
from sqlalchemy import select

from service.broker import broker_epoch, make_celery, publish_units
from service.config import Settings
from service.db import accounts, jobs, outbox, units
from service.db.migrate import upgrade
from service.db.models import Team
from service.db.session import dispose_all, session_scope
from tests.integration.servers import REDIS_SERVER, PrivateRedis

SPEC = {
    "systems": ["paper-stable"],
    "sigma_w": [1.0],
    "N": [10, 20, 30],
    "reps": 2,
    "estimators": ["ols"],
    "seed": 1,
}


@pytest.fixture
def db(tmp_path):
    url = f"sqlite:///{tmp_path / 'relay.db'}"
    upgrade(url)
    with session_scope(url) as s:
        accounts.create_team(s, "lab")
    yield url
    dispose_all()


def _job(url) -> list[int]:
    with session_scope(url) as s:
        team = s.scalar(select(Team).where(Team.name == "lab"))
        job, _ = jobs.create_job(s, team_id=team.id, user_id=None, spec=SPEC)
        s.flush()
        return jobs.unit_ids_of_job(s, job.id)


def test_units_published_before_the_broker_epoch_are_republished_at_once(db):
    ids = _job(db)
    t_pub = datetime.now(UTC)
    with session_scope(db) as s:
        outbox.mark_published(s, ids, now=t_pub)
    soon = t_pub + timedelta(seconds=5)
    with session_scope(db) as s:
        # published 5 s ago: nothing to do (the retry time is 600 s) ...
        assert outbox.units_to_publish(s, now=soon, retry_seconds=600) == []
        # ... unless the broker's data is younger than the publication: lost, re-publish
        assert (
            outbox.units_to_publish(
                s, now=soon, lost_before=t_pub + timedelta(seconds=2), retry_seconds=600
            )
            == ids
        )
        # an epoch older than the publication (the broker kept its data): nothing
        assert (
            outbox.units_to_publish(
                s, now=soon, lost_before=t_pub - timedelta(hours=1), retry_seconds=600
            )
            == []
        )
        # once re-published after the epoch they are not selected again in the same tick
        outbox.mark_published(s, ids[:2], now=t_pub + timedelta(seconds=3))
        assert (
            outbox.units_to_publish(
                s, now=soon, lost_before=t_pub + timedelta(seconds=2), retry_seconds=600
            )
            == ids[2:]
        )
        # an epoch in the future (clock skew) never selects units published later than now
        outbox.mark_published(s, ids, now=soon + timedelta(seconds=1))
        assert (
            outbox.units_to_publish(
                s, now=soon, lost_before=soon + timedelta(hours=1), retry_seconds=600
            )
            == []
        )


def test_broker_epoch_is_none_for_the_filesystem_broker(tmp_path):
    app = make_celery(Settings(BROKER_URL="filesystem://", BROKER_DIR=str(tmp_path / "b")))
    assert broker_epoch(app) is None


@pytest.fixture(scope="module")
def private_redis(tmp_path_factory):
    """A throw-away redis-server on a spare loopback port (never the machine's own)."""
    if REDIS_SERVER is None:
        pytest.skip("redis-server not installed")
    server = PrivateRedis(tmp_path_factory.mktemp("redis"))
    try:
        server.start()
        yield server
    finally:
        server.stop()


def test_broker_epoch_lives_and_dies_with_the_redis_data(private_redis):
    import redis

    app = make_celery(Settings(BROKER_URL=private_redis.url))
    r = redis.Redis.from_url(private_redis.url)
    try:
        r.flushdb()
        before = datetime.now(UTC)
        first = broker_epoch(app)  # missing: created now
        assert before - timedelta(seconds=1) <= first <= datetime.now(UTC)
        assert broker_epoch(app) == first  # kept while the data lives
        r.flushdb()  # what a restart without persistence does to the queue and the marker
        assert broker_epoch(app) > first
    finally:
        r.close()


def test_publishing_creates_the_marker_first(private_redis):
    """Units the API publishes into a fresh broker are not taken for lost by the relay."""
    import redis

    app = make_celery(Settings(BROKER_URL=private_redis.url))
    r = redis.Redis.from_url(private_redis.url)
    try:
        r.flushdb()
        t0 = datetime.now(UTC)
        assert publish_units(app, [1, 2, 3]) == [1, 2, 3]
        assert r.llen("svrobs") == 3
        epoch = broker_epoch(app)
        assert t0 - timedelta(seconds=1) <= epoch <= datetime.now(UTC)
    finally:
        r.flushdb()
        r.close()


def test_a_unit_given_up_quotes_what_killed_its_worker(db):
    from service.db.models import Job, WorkUnit

    uid = _job(db)[0]
    for _ in range(2):
        with session_scope(db) as s:
            assert units.start_unit(s, uid, "w@host", 60, max_attempts=2) is not None
        with session_scope(db) as s:  # what worker.tasks.UnitRequest does when it is lost
            units.note_unit_error(
                s, uid, "WorkerLostError: Worker exited prematurely: signal 11 (SIGSEGV)"
            )
    with session_scope(db) as s:
        assert units.start_unit(s, uid, "w@host", 60, max_attempts=2) is None
    with session_scope(db) as s:
        unit = s.get(WorkUnit, uid)
        job = s.get(Job, unit.job_id)
        assert unit.status == "failed" and job.status == "failed"
        assert "gave up after 2 attempts" in job.error
        assert "signal 11 (SIGSEGV)" in job.error and "unit 0 (system=paper-stable" in job.error
        # only a running unit is annotated
        units.note_unit_error(s, uid, "late")
    with session_scope(db) as s:
        assert "late" not in s.get(WorkUnit, uid).error
