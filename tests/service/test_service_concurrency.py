"""Real concurrent transactions (separate connections, committed data, cleaned up):
a doubled beat tick makes one job; two units finishing together finish the job."""

from __future__ import annotations

import threading
from datetime import UTC, datetime

import pytest
from sqlalchemy import delete, func, select
from sqlalchemy.orm import sessionmaker

from service.config import get_settings
from service.db import accounts, jobs, units
from service.db.job_delete import delete_job
from service.db.models import Job, Result, Schedule, Team
from svrobs_lab import schedules as lab_schedules
from tests.service.svc_fakes import fake_records
from tests.service.svc_helpers import SMALL_SPEC


@pytest.fixture
def real_sessions(engine):
    maker = sessionmaker(bind=engine, expire_on_commit=False)
    team_ids = []
    yield maker, team_ids
    with maker() as s:
        for tid in team_ids:  # results rows have no foreign key to cascade on
            jobs_of = select(Job.id).where(Job.team_id == tid)
            s.execute(delete(Result).where(Result.job_id.in_(jobs_of)))
            s.execute(delete(Team).where(Team.id == tid))
        s.commit()


def _parallel(fns):
    errors = []
    barrier = threading.Barrier(len(fns))

    def wrap(fn):
        try:
            barrier.wait(5)
            fn()
        except Exception as exc:  # noqa: BLE001 - every thread's error is asserted on below
            errors.append(exc)

    threads = [threading.Thread(target=wrap, args=(f,)) for f in fns]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert not errors, errors


def test_two_ticks_at_once_make_one_job(real_sessions):
    maker, team_ids = real_sessions
    with maker() as s:
        team = accounts.create_team(s, "concurrent-beat")
        team_ids.append(team.id)
        s.add(
            Schedule(
                team_id=team.id,
                name="n",
                cron="*/5 * * * *",
                timezone="UTC",
                spec_template=SMALL_SPEC,
                tags=[],
                created_at=datetime(2024, 1, 1, tzinfo=UTC),
            )
        )
        s.commit()
    now = datetime(2024, 6, 1, 12, 7, tzinfo=UTC)

    def tick():
        with maker() as s:
            lab_schedules.create_due_jobs(get_settings(), s, now)
            s.commit()

    _parallel([tick, tick, tick])
    with maker() as s:
        assert s.scalar(select(func.count(Job.id)).where(Job.team_id == team_ids[0])) == 1


def _team_with_a_job(s, team_ids: list, name: str):
    """A new team (cleaned up by real_sessions) and a committed job of SMALL_SPEC."""
    team = accounts.create_team(s, name)
    team_ids.append(team.id)
    job, _ = jobs.create_job(s, team_id=team.id, user_id=None, spec=SMALL_SPEC)
    s.commit()
    return team, job


def test_units_finishing_together_finish_the_job(real_sessions):
    maker, team_ids = real_sessions
    with maker() as s:
        _, job = _team_with_a_job(s, team_ids, "concurrent-units")
        ids = jobs.unit_ids_of_job(s, job.id)
        for uid in ids:
            units.start_unit(s, uid, "w", 60, max_attempts=0)
        s.commit()
        payloads = {uid: units.start_unit(s, uid, "w", 60, max_attempts=0) for uid in ids}
        s.commit()

    def finisher(uid):
        def fn():
            with maker() as s:
                spec, payload = payloads[uid]
                units.complete_unit(s, uid, fake_records(spec, payload))
                s.commit()

        return fn

    _parallel([finisher(u) for u in ids])
    with maker() as s:
        j = s.get(Job, job.id)
        assert j.status == "succeeded" and j.progress_done == len(ids)


def test_a_deleted_jobs_running_unit_stores_nothing_in_the_next_job(real_sessions):
    """A unit computing while its job is cancelled and deleted: the next job made gets
    new job and unit ids (SQLite too: NEVER_REUSED), so the old unit's completion
    finds no unit and stores nothing, in either job."""
    maker, team_ids = real_sessions
    with maker() as s:
        team, old = _team_with_a_job(s, team_ids, "deleted-while-running")
        uid = jobs.unit_ids_of_job(s, old.id)[-1]
        spec, payload = units.start_unit(s, uid, "w", 60, max_attempts=0)
        s.commit()
        jobs.cancel_job(s, jobs.lock_job(s, old.id))
        s.commit()
        delete_job(s, jobs.lock_job(s, old.id))
        s.commit()
        new, _ = jobs.create_job(s, team_id=team.id, user_id=None, spec=SMALL_SPEC)
        s.commit()
        new_units = jobs.unit_ids_of_job(s, new.id)
        assert new.id > old.id and min(new_units) > uid
        assert units.complete_unit(s, uid, fake_records(spec, payload)) is False
        s.commit()
        stored = s.scalar(select(func.count()).select_from(Result).where(Result.job_id == new.id))
        assert stored == 0 and s.get(Job, new.id).status == "queued"
