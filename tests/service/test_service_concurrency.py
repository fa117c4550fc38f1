"""Real concurrent transactions (separate connections, committed data, cleaned up):
a doubled beat tick makes one job; two units finishing together finish the job; a
row deleted between a request's read and its write is a NotFound."""

from __future__ import annotations

import threading
from datetime import UTC, datetime

import pytest
from sqlalchemy import delete, func, select
from sqlalchemy.orm import sessionmaker

from service.config import get_settings
from service.db import accounts, jobs, units
from service.db.job_delete import delete_job
from service.db.models import TAG_MAX, Job, Result, Schedule, Team
from svrobs_lab import schedules as lab_schedules
from svrobs_lab import shares as lab_shares
from svrobs_lab.auth import Caller
from svrobs_lab.errors import NotFound
from svrobs_lab.jobs import Submission
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


# A row deleted by another connection between a request's read and its write: the
# wrapped reader reads, then ``remove`` deletes and commits on a connection of its own.
def _deleted_after_read(monkeypatch, module, name: str, maker, remove) -> None:
    read = getattr(module, name)

    def read_then_deleted(session, caller, object_id, **kwargs):
        found = read(session, caller, object_id, **kwargs)
        if not kwargs.get("lock"):  # the first, unlocked read only
            session.commit()  # the request's read transaction ends (SQLite: no stale snapshot)
            with maker() as other:
                remove(other, object_id)
                other.commit()
        return found

    monkeypatch.setattr(module, name, read_then_deleted)


def _schedule(s, team_ids: list, name: str, schedule_name: str = "nightly") -> tuple:
    team = accounts.create_team(s, name)
    team_ids.append(team.id)
    sched = Schedule(
        team_id=team.id,
        name=schedule_name,
        cron="*/5 * * * *",
        timezone="UTC",
        spec_template=SMALL_SPEC,
        tags=[],
        created_at=datetime(2024, 1, 1, tzinfo=UTC),
    )
    s.add(sched)
    s.commit()
    return Caller(key_id=0, team_id=team.id, user_id=None, is_admin=False), sched.id


def _submission(s, caller) -> Submission:
    """A request's submission whose publishing after the response is not needed here."""
    return Submission(
        session=s,
        caller=caller,
        settings=get_settings(),
        publisher=None,
        session_factory=None,
        later=lambda *args: None,
    )


def _drop_schedule(s, schedule_id):
    s.execute(delete(Schedule).where(Schedule.id == schedule_id))


def test_a_share_of_a_job_deleted_meanwhile_is_not_found(real_sessions, monkeypatch):
    """The job is read, then deleted and committed elsewhere before the link is
    inserted: NotFound (404), not the foreign key's IntegrityError (a 500 on PostgreSQL)."""
    maker, team_ids = real_sessions
    with maker() as s:
        team, job = _team_with_a_job(s, team_ids, "share-vs-delete")
        jobs.cancel_job(s, jobs.lock_job(s, job.id))
        s.commit()
    _deleted_after_read(
        monkeypatch, lab_shares, "team_job", maker, lambda o, i: delete_job(o, jobs.lock_job(o, i))
    )
    caller = Caller(key_id=0, team_id=team.id, user_id=None, is_admin=False)
    with maker() as s, pytest.raises(NotFound):
        lab_shares.create(s, caller, get_settings(), job.id, days=1.0)


@pytest.mark.parametrize("action", ["update", "run_now"])
def test_a_schedule_deleted_meanwhile_is_not_found(real_sessions, monkeypatch, action):
    """The schedule is read, then deleted and committed elsewhere: changing it or
    running it now is NotFound (404), not a StaleDataError or a foreign key's
    IntegrityError (500s on PostgreSQL)."""
    maker, team_ids = real_sessions
    with maker() as s:
        caller, sid = _schedule(s, team_ids, f"schedule-{action}-vs-delete")
    _deleted_after_read(monkeypatch, lab_schedules, "team_schedule", maker, _drop_schedule)
    with maker() as s, pytest.raises(NotFound):
        if action == "update":
            lab_schedules.update(s, caller, get_settings(), sid, {"enabled": False})
        else:
            lab_schedules.run_now(_submission(s, caller), sid)
    with maker() as s:
        assert s.scalar(select(func.count(Job.id)).where(Job.team_id == caller.team_id)) == 0


def test_a_schedule_with_the_longest_name_runs_and_others_still_run(real_sessions):
    """A 200-character schedule name: its job's name is cut to its column's 200
    characters and its tag to the 100 a tag may have (PostgreSQL refuses longer ones,
    and that error must not undo every team's runs); the other team's schedule runs in
    the same tick."""
    maker, team_ids = real_sessions
    with maker() as s:
        long_caller, long_id = _schedule(s, team_ids, "long-name", "L" * 200)
        other_caller, other_id = _schedule(s, team_ids, "short-name")
    now = datetime(2024, 6, 1, 12, 7, tzinfo=UTC)
    with maker() as s:
        made = lab_schedules.create_due_jobs(get_settings(), s, now)
        s.commit()
        assert {j.schedule_id for j in made} == {long_id, other_id}
        job = next(j for j in made if j.schedule_id == long_id)
        assert len(job.name) == 200 and job.name.endswith("… @ 2024-06-01T12:05:00Z")
        assert job.name.startswith("L" * 170)
        tag = next(t for t in job.tags if t.startswith("schedule:"))
        assert len(tag) == TAG_MAX and tag.endswith("L…")
        out = lab_schedules.run_now(_submission(s, long_caller), long_id)
        assert len(out["name"]) == 200 and out["name"].endswith(" (run now)")
