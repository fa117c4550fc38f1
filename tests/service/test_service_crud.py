"""service.db: jobs, units, idempotent completion, the outbox, schedules, cancel."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest
from sqlalchemy import delete, func, select

from service.config import get_settings
from service.db import jobs, outbox, results_store, schedules, units
from service.db.models import Job, Result, Schedule, ScheduleRun, Summary, WorkUnit
from svrobs_core import planning
from svrobs_core.errors import SpecError
from svrobs_core.parsing import parse_spec
from svrobs_lab import errors
from svrobs_lab import schedules as lab_schedules
from tests.service.svc_fakes import fake_records, run_job_units
from tests.service.svc_helpers import SMALL_SPEC, SMALL_UNITS


def _count(session, model, **where):
    q = select(func.count()).select_from(model)
    for k, v in where.items():
        q = q.where(getattr(model, k) == v)
    return session.scalar(q)


def test_create_job_writes_job_and_units(session, make_account):
    acc = make_account()
    job, created = jobs.create_job(
        session,
        team_id=acc.team.id,
        user_id=acc.user.id,
        spec=SMALL_SPEC,
        name="small",
        tags=["a", "b", "a"],
    )
    session.commit()
    assert created and job.status == "queued"
    assert job.n_cells == parse_spec(SMALL_SPEC).n_cells == 2 * 2 * 2 * 3 * 3
    assert job.spec == parse_spec(SMALL_SPEC).to_dict()
    assert job.tags == ["a", "b"]
    assert job.provenance["seed"] == 7 and job.provenance["version"]
    assert {"python", "numpy", "git_commit"} <= set(job.provenance)
    assert _count(session, WorkUnit, job_id=job.id) == job.progress_total == SMALL_UNITS


def test_idempotency_key_returns_same_job(session, make_account):
    acc = make_account()
    kw = dict(team_id=acc.team.id, user_id=acc.user.id, spec=SMALL_SPEC, idempotency_key="k1")
    a, _ = jobs.create_job(session, **kw)
    session.commit()
    b, created = jobs.create_job(session, **kw)
    session.commit()
    assert a.id == b.id and not created
    assert _count(session, Job, team_id=acc.team.id) == 1
    assert _count(session, WorkUnit, job_id=a.id) == SMALL_UNITS
    with pytest.raises(errors.IdempotencyConflict):
        jobs.create_job(session, **{**kw, "spec": {**SMALL_SPEC, "seed": 8}})
    # the key is per team
    other = make_account()
    c, _ = jobs.create_job(session, **{**kw, "team_id": other.team.id, "user_id": other.user.id})
    assert c.id != a.id


def test_bad_and_too_large_specs_raise(session, make_account):
    acc = make_account()
    with pytest.raises(SpecError) as e:
        jobs.create_job(
            session, team_id=acc.team.id, user_id=None, spec={**SMALL_SPEC, "gamma": [0.1, -1]}
        )
    assert e.value.field == "gamma[1]"
    with pytest.raises(errors.JobTooLarge) as e:
        jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC, max_cells=10)
    assert e.value.field == "spec"
    assert _count(session, Job, team_id=acc.team.id) == 0


def test_queued_job_cap(session, make_account):
    acc = make_account()
    for _ in range(2):
        jobs.create_job(
            session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC, max_active_jobs=2
        )
    with pytest.raises(errors.QuotaExceeded):
        jobs.create_job(
            session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC, max_active_jobs=2
        )


def test_unit_lifecycle_and_double_completion(session, make_account):
    acc = make_account()
    job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC)
    session.commit()
    ids = jobs.unit_ids_of_job(session, job.id)
    spec, payload = units.start_unit(session, ids[0], "w1", 60, max_attempts=0)
    session.commit()
    session.refresh(job)
    assert job.status == "running" and job.started_at is not None
    recs = fake_records(spec, payload)
    units.complete_unit(session, ids[0], recs)
    units.complete_unit(session, ids[0], recs)  # a redelivered task
    session.commit()
    assert _count(session, Result, job_id=job.id) == len(recs)
    session.refresh(job)
    assert job.progress_done == 1 and job.status == "running"
    assert (
        units.start_unit(session, ids[0], "w2", 60, max_attempts=0) is None
    )  # done units are skipped
    run_job_units(session, job.id)
    session.refresh(job)
    assert job.status == "succeeded" and job.progress_done == job.progress_total == SMALL_UNITS
    assert job.finished_at and "run_seconds" in job.timings
    assert _count(session, Result, job_id=job.id) == job.n_cells
    # one row per cell even after a full second pass
    for uid in ids:
        unit = session.get(WorkUnit, uid)
        units.complete_unit(session, uid, fake_records(job.spec, unit.payload))
    session.commit()
    assert _count(session, Result, job_id=job.id) == job.n_cells
    groups = session.scalars(select(Summary).where(Summary.job_id == job.id)).all()
    assert len(groups) == 2 * 2 * 2 * 3  # system x sigma_w x N x (ols, svr 0.05, svr 0.1)
    assert all(g.count == 3 for g in groups)
    ols = [g for g in groups if g.estimator == "ols"]
    assert all(g.gamma is None and g.gamma_key == -1 for g in ols)


def test_stored_values_round_trip(session, make_account):
    acc = make_account()
    job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC)
    session.commit()
    uid = jobs.unit_ids_of_job(session, job.id)[0]
    spec, payload = units.start_unit(session, uid, "w", 60, max_attempts=0)
    recs = fake_records(spec, payload)
    units.complete_unit(session, uid, recs)
    session.commit()
    got = {
        (r["system"], r["sigma_w"], r["N"], r["estimator"], r["gamma"], r["rep"]): r
        for r in results_store.load_records(session, job.id)
    }
    for rec in recs:
        back = got[
            (rec["system"], rec["sigma_w"], rec["N"], rec["estimator"], rec["gamma"], rec["rep"])
        ]
        assert back["A_hat"] == rec["A_hat"]  # bit-identical through the float64 bytes
        assert back["rmse_A"] == rec["rmse_A"]
        assert back["rmse_B"] is None  # NaN is stored as NULL
        assert back["thm1_holds_A"] is rec["thm1_holds_A"]
        assert back["seed_key"] == rec["seed_key"]


def test_fail_unit_final_names_cells(session, make_account):
    acc = make_account()
    job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC)
    session.commit()
    ids = jobs.unit_ids_of_job(session, job.id)
    units.start_unit(session, ids[1], "w", 60, max_attempts=0)
    units.fail_unit(session, ids[1], "boom", final=False)
    assert session.get(WorkUnit, ids[1]).status == "pending"
    units.fail_unit(session, ids[1], "boom", final=True)
    session.commit()
    session.refresh(job)
    assert job.status == "failed"
    assert "boom" in job.error and "system=paper-stable" in job.error and "N=[20, 40]" in job.error
    assert session.get(WorkUnit, ids[2]).status == "cancelled"
    assert units.start_unit(session, ids[0], "w", 60, max_attempts=0) is None


def test_max_attempts_fails_the_unit(session, make_account):
    acc = make_account()
    job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC)
    uid = jobs.unit_ids_of_job(session, job.id)[0]
    for _ in range(3):
        assert units.start_unit(session, uid, "w", 60, max_attempts=3) is not None
    assert units.start_unit(session, uid, "w", 60, max_attempts=3) is None
    session.refresh(job)
    assert job.status == "failed" and "3 attempts" in job.error


def test_relay_publishes_unpublished_and_expired(session, make_account):
    acc = make_account()
    job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC)
    session.commit()
    ids = jobs.unit_ids_of_job(session, job.id)
    assert outbox.units_to_publish(session, retry_seconds=600) == ids
    outbox.mark_published(session, ids[:5])
    assert outbox.units_to_publish(session, retry_seconds=600) == ids[5:]
    outbox.mark_published(session, ids[5:])
    assert outbox.units_to_publish(session, retry_seconds=600) == []
    later = datetime.now(UTC) + timedelta(hours=2)
    # published but never started -> re-published after the retry time
    assert outbox.units_to_publish(session, now=later, retry_seconds=600) == ids
    units.start_unit(session, ids[0], "w", lease_seconds=60, max_attempts=0)
    assert ids[0] not in outbox.units_to_publish(session, retry_seconds=600)
    assert ids[0] in outbox.units_to_publish(
        session, now=later, retry_seconds=600
    )  # the lease ran out
    outbox.mark_published(session, [ids[0]], now=later)
    assert session.get(WorkUnit, ids[0]).status == "pending"
    jobs.cancel_job(session, job)
    assert outbox.units_to_publish(session, now=later, retry_seconds=600) == []


def test_a_starting_worker_ends_the_leases_of_the_units_its_name_left_running(
    session, make_account
):
    """``expire_leases_of``: the running units of that node name only, re-published by
    the next relay (their lease is over); another worker's and a done unit untouched."""
    acc = make_account()
    job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC)
    session.commit()
    ids = jobs.unit_ids_of_job(session, job.id)
    outbox.mark_published(session, ids)
    for uid, name in zip(ids[:3], ("w1@host", "w1@host", "w2@host")):
        units.start_unit(session, uid, name, lease_seconds=7200, max_attempts=0)
    assert outbox.units_to_publish(session, retry_seconds=600) == []
    assert sorted(units.expire_leases_of(session, "w1@host")) == ids[:2]
    assert outbox.units_to_publish(session, retry_seconds=600) == ids[:2]
    assert units.expire_leases_of(session, "w3@host") == []
    assert session.get(WorkUnit, ids[2]).status == "running"


def test_cancel_job(session, make_account):
    acc = make_account()
    job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC)
    session.commit()
    ids = jobs.unit_ids_of_job(session, job.id)
    units.start_unit(session, ids[0], "w", 60, max_attempts=0)
    job = jobs.cancel_job(session, job)
    session.commit()
    assert job.status == "cancelled" and job.finished_at
    statuses = {
        u.status for u in session.scalars(select(WorkUnit).where(WorkUnit.job_id == job.id))
    }
    assert statuses == {"cancelled"}  # the running one too: its worker stops it
    assert units.start_unit(session, ids[1], "w", 60, max_attempts=0) is None
    # a running unit that finishes anyway stores nothing; the job stays cancelled
    spec = job.spec
    units.complete_unit(session, ids[0], fake_records(spec, session.get(WorkUnit, ids[0]).payload))
    session.refresh(job)
    assert job.status == "cancelled" and job.cells_done == 0
    assert session.scalar(select(func.count()).where(Result.job_id == job.id)) == 0


def _schedule(session, acc, **kw):
    s = Schedule(
        team_id=acc.team.id,
        user_id=acc.user.id,
        name=kw.pop("name", "nightly"),
        cron=kw.pop("cron", "0 2 * * *"),
        timezone=kw.pop("timezone", "Europe/Paris"),
        spec_template=kw.pop("spec_template", SMALL_SPEC),
        tags=["sweep"],
        created_at=kw.pop("created_at", datetime(2024, 1, 1, tzinfo=UTC)),
        **kw,
    )
    session.add(s)
    session.flush()
    return s


def test_due_schedule_ticked_twice_gives_one_job(session, make_account):
    acc = make_account()
    s = _schedule(session, acc)
    session.commit()
    now = datetime(2024, 6, 1, 0, 30, tzinfo=UTC)  # 02:30 in Paris (CEST)
    first = lab_schedules.create_due_jobs(get_settings(), session, now)
    session.commit()
    second = lab_schedules.create_due_jobs(get_settings(), session, now + timedelta(minutes=1))
    session.commit()
    mine = [j for j in first if j.team_id == acc.team.id]
    assert len(mine) == 1 and not [j for j in second if j.team_id == acc.team.id]
    job = mine[0]
    assert job.schedule_id == s.id and "schedule:nightly" in job.tags
    runs = session.scalars(select(ScheduleRun).where(ScheduleRun.schedule_id == s.id)).all()
    assert len(runs) == 1 and runs[0].job_id == job.id
    assert runs[0].due_at == datetime(2024, 6, 1, 0, 0, tzinfo=UTC)
    assert _count(session, Job, schedule_id=s.id) == 1
    # the next day is a new run
    nxt = lab_schedules.create_due_jobs(get_settings(), session, now + timedelta(days=1))
    assert len([j for j in nxt if j.team_id == acc.team.id]) == 1


def test_schedule_not_due_before_creation_or_disabled(session, make_account):
    acc = make_account()
    created = datetime(2024, 6, 1, 0, 10, tzinfo=UTC)
    _schedule(session, acc, created_at=created)
    _schedule(session, acc, name="off", enabled=False)
    made = lab_schedules.create_due_jobs(get_settings(), session, created + timedelta(minutes=5))
    assert not [j for j in made if j.team_id == acc.team.id]


def test_schedule_with_broken_template_records_error(session, make_account):
    acc = make_account()
    s = _schedule(session, acc, spec_template={"systems": ["nope"], "sigma_w": [1], "N": [5]})
    made = lab_schedules.create_due_jobs(
        get_settings(), session, datetime(2024, 6, 1, 3, tzinfo=UTC)
    )
    assert not [j for j in made if j.team_id == acc.team.id]
    run = session.scalar(select(ScheduleRun).where(ScheduleRun.schedule_id == s.id))
    assert run.job_id is None and "systems[0]" in run.error


def test_latest_due_in_time_zone():
    now = datetime(2024, 1, 15, 1, 30, tzinfo=UTC)  # 02:30 Paris (CET)
    assert schedules.latest_due("0 2 * * *", "Europe/Paris", now) == datetime(
        2024, 1, 15, 1, 0, tzinfo=UTC
    )
    exact = datetime(2024, 1, 15, 1, 0, tzinfo=UTC)
    assert schedules.latest_due("0 2 * * *", "Europe/Paris", exact) == exact


def test_record_to_row_coerces_every_field_to_its_column_type():
    import math as _m

    from service.db.results_store import record_to_row
    from svrobs_core.records import BOOL_FIELDS, empty_record

    rec = empty_record()
    rec.update(
        system="s",
        estimator="svr",
        gamma=0.1,
        N=10.0,
        N0=90,
        rep=1,
        sigma_w=1,
        rmse_A=float("nan"),
        rmse_B=float("inf"),
        eps_A=0.5,
        thm1_holds_A=0.25,
        thm1_holds_B=0.0,
        certified=True,
        A_hat=[[1.0, float("nan")]],
        B_hat=[[1.0], [2.0]],
    )
    row = record_to_row(7, rec)
    assert row["thm1_holds_A"] is True and row["thm1_holds_B"] is False
    assert row["certified"] is True and all(type(row[f]) in (bool, type(None)) for f in BOOL_FIELDS)
    assert row["N"] == 10 and type(row["N"]) is int and row["sigma_w"] == 1.0
    assert row["rmse_A"] is None and row["rmse_B"] is None and row["eps_A"] == 0.5
    assert row["A_hat"] == [[1.0, None]] and row["B_hat"] == [[1.0], [2.0]]
    assert not any(isinstance(v, float) and not _m.isfinite(v) for v in row.values())


def test_unit_columns_store_the_same_rows_as_records(session, make_account):
    """The columnar write (a worker's UnitResult) = the record-dict write, cell by cell,
    = the core's records with NaN as null; every stage, so every field is exercised."""
    from svrobs_core.records import json_value
    from svrobs_core.runner import run_unit_result

    spec = {
        **SMALL_SPEC,
        "systems": ["paper-unstable"],
        "sigma_w": [1.0],
        "N": [40],
        "reps": 2,
        "stages": ["estimate", "bounds", "gain", "cost", "sls"],
        "mc_reps": 1,
        "mc_runs": 20,
    }
    acc = make_account()
    got = []
    for as_columns in (True, False):
        job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=spec)
        session.commit()
        for uid in jobs.unit_ids_of_job(session, job.id):
            spec_dict, payload = units.start_unit(session, uid, "w", 60, max_attempts=0)
            result = run_unit_result(parse_spec(spec_dict), payload)
            units.complete_unit(session, uid, result if as_columns else result.records())
        session.commit()
        got.append(
            {
                (r["N"], r["estimator"], r["gamma"], r["rep"]): r
                for r in results_store.load_records(session, job.id)
            }
        )
    columns, records = got
    assert len(columns) == 2 * 3 and columns == records
    want = run_unit_result(parse_spec(spec), planning.plan_units(parse_spec(spec))[0]).records()
    for rec in want:
        stored = columns[(rec["N"], rec["estimator"], rec["gamma"], rec["rep"])]
        assert stored == {k: json_value(v) for k, v in rec.items()}
    assert any(v is not None for r in columns.values() for v in (r["L"], r["J_exact"]))


def test_clean_column_matches_the_per_value_cleaning():
    import numpy as np

    from service.db.results_store import _clean_column, _clean_scalar

    cases = {
        "rmse_A": [
            [0.5, None, 1.0],
            [0.5, float("nan")],
            [np.float64(2.0), 1.0],
            [float("inf"), None],
            [None, None],
        ],
        "certified": [[True, None, False], [np.bool_(True), False], [1.0, 0.0]],
        "N": [[10, 20], [10.0, 20], [np.int64(3)]],
    }
    for f, cols in cases.items():
        for col in cols:
            out = _clean_column(f, list(col))
            want = [_clean_scalar(f, v) for v in col]
            assert out == want and [type(x) for x in out] == [type(x) for x in want], (f, col)


@pytest.mark.parametrize("split_reps", [False, True, "lost"])
def test_stored_summaries_equal_a_summary_of_all_results(
    session, make_account, monkeypatch, split_reps
):
    """Units holding every repetition of their groups store those groups' summaries
    as they finish (twice for a redelivered unit); units split by repetitions leave it
    to the end, and so does a job where a unit stored none ("lost": e.g. completed by
    an older worker). Either way the stored summaries = summarize() of the records."""
    import functools

    from svrobs_core.records import summarize

    if split_reps is True:  # 1 repetition per unit: every group spans three units
        # (service.db.jobs.admit plans through svrobs_core.admission.admit)
        split = functools.partial(planning.plan_units, max_cells=6)
        monkeypatch.setattr(planning, "plan_units", split)
    acc = make_account()
    job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC)
    session.commit()
    rows = session.scalars(select(WorkUnit).where(WorkUnit.job_id == job.id)).all()
    assert any(u.payload["reps"] != [0, 3] for u in rows) == (split_reps is True)
    first = rows[0]
    spec, payload = units.start_unit(session, first.id, "w", 60, max_attempts=0)
    units.complete_unit(session, first.id, fake_records(spec, payload))
    units.complete_unit(session, first.id, fake_records(spec, payload))  # redelivered
    if split_reps == "lost":
        session.execute(delete(Summary).where(Summary.job_id == job.id))
    run_job_units(session, job.id)
    session.commit()
    want = summarize(results_store.load_records(session, job.id))
    stored = session.scalars(select(Summary).where(Summary.job_id == job.id)).all()
    got = {(s.system, s.sigma_w, s.N, s.estimator, s.gamma): (s.count, s.stats) for s in stored}
    assert len(got) == len(stored) == len(want) == 24
    for g in want:
        count, stats = got[tuple(g[k] for k in ("system", "sigma_w", "N", "estimator", "gamma"))]
        assert count == g["count"] == 3
        for f, st in g["stats"].items():
            assert stats[f]["count"] == st["count"]
            for k in ("mean", "std"):
                assert stats[f][k] == (None if st[k] is None else pytest.approx(st[k], rel=1e-12))
