"""Jobs on datasets through the service, on SQLite and PostgreSQL: a dataset simulated
from a known system (no preset) is uploaded as a file, a job on it is submitted over
REST and its units are computed by the worker's code (``svrobs_lab.units``) and
stored; its records read back over REST equal the core's measured path run in this
process on the same arrays, bit for bit (m = 0 too: n x 0 matrices). The validation
endpoint serves what ``validation_summary`` gives in process, computed once. The
report, schedules, the job limits and the unit plan under the memory cap take dataset
specs."""

from __future__ import annotations

import contextlib
import json
import uuid
from datetime import UTC, datetime

import numpy as np
import pytest
from sqlalchemy import func, select

from service.config import get_settings
from service.db import datasets as dataset_store
from service.db import jobs as job_store
from service.db import units
from service.db.models import Job, JobValidation, Schedule, ScheduleRun, WorkUnit
from svrobs_core import RECORD_FIELDS, parse_spec
from svrobs_core.measured import MeasuredData, run_measured_unit, validation_summary
from svrobs_lab import schedules as lab_schedules
from svrobs_lab.datasets.overview import PLOTTED_VALUES
from svrobs_lab.units import after_unit, compute_unit
from svrobs_lab.validation import PLOTTED_ROLLOUTS, summarize
from tests.datasets import files
from tests.integration.stack import cell_key, same
from tests.service.svc_helpers import SMALL_SPEC, track_sessions

API = "/api/v1"
# a system of no preset: 3 states, 2 inputs, stable
A_TRUE = np.array([[0.7, 0.2, 0.0], [-0.1, 0.6, 0.3], [0.05, 0.0, 0.5]])
B_TRUE = np.array([[1.0, 0.0], [0.3, -0.5], [0.0, 0.8]])


def simulate(seed: int, *, rollouts: int, T: int, m: int = 2, sigma_w: float = 0.2):
    """Rollouts of A_TRUE, B_TRUE[:, :m] with Gaussian inputs and noise (seeded)."""
    return files.simulate(A_TRUE, B_TRUE[:, :m], seed, lengths=(T,) * rollouts, sigma_w=sigma_w)


def upload(client, acc, name: str, data: bytes) -> dict:
    r = client.post(
        f"{API}/datasets",
        files={"file": (name, data)},
        data={"name": f"ds-{uuid.uuid4().hex[:6]}"},
        headers=acc.headers,
    )
    assert r.status_code == 201, r.text
    return r.json()


@pytest.fixture
def scope(session_factory):
    """``session_scope`` on the test's connection (what the worker passes)."""

    @contextlib.contextmanager
    def make(write: bool = True):
        s = session_factory(write)
        try:
            yield s
            s.commit()
        except BaseException:
            s.rollback()
            raise
        finally:
            s.close()

    return make


def run_worker_units(session, scope, job_id: int) -> int:
    """Every unit of the job as the worker runs it: claim, compute on the stored
    arrays, store, then the job's validation once."""
    n = 0
    for uid in job_store.unit_ids_of_job(session, job_id, pending_only=False):
        spec, payload = units.start_unit(session, uid, "w1", 60, max_attempts=0)
        session.commit()
        result, data = compute_unit(scope, spec, payload)
        assert units.complete_unit(session, uid, result)
        session.commit()
        after_unit(scope, uid, spec, data)
        n += 1
    return n


def rest_records(client, acc, job_id: int) -> dict:
    r = client.get(f"{API}/jobs/{job_id}/results", params={"format": "jsonl"}, headers=acc.headers)
    assert r.status_code == 200, r.text
    return {cell_key(rec): rec for rec in map(json.loads, r.text.splitlines())}


def in_process(spec: dict, X, U) -> dict:
    """The measured path of the core on the file's arrays, in this process, through
    the JSON round trip the API serves (one unit holding the whole grid)."""
    parsed = parse_spec(spec)
    unit = {"system": 0, "sigma_w": 0, "N": list(parsed.N), "reps": [0, parsed.reps]}
    records = run_measured_unit(parsed, unit, MeasuredData(X=X, U=U)).records()
    return {cell_key(r): json.loads(json.dumps(r, allow_nan=False)) for r in records}


def assert_same(got: dict, want: dict) -> None:
    assert set(got) == set(want) and got
    diffs = [d for k, w in want.items() for f in RECORD_FIELDS for d in same(got[k][f], w[f], f)]
    assert not diffs, diffs[:10]


SPEC = {
    "N": [6, 12],
    "holdout": 3,
    "reps": 3,
    "gamma": [0.05],
    "estimators": ["ols", "svr"],
    "stages": ["estimate", "bounds", "gain", "cost", "cost_bound"],
    "seed": 4,
}


def test_dataset_job_records_equal_the_core_on_the_same_arrays(
    client, session, scope, make_account, settings
):
    acc = make_account()
    X, U = simulate(11, rollouts=15, T=30)
    ds = upload(client, acc, "plant.csv", files.csv_bytes(X, U))
    spec = {**SPEC, "dataset": ds["id"], "sigma_w": "estimate"}
    r = client.post(f"{API}/jobs", json={**spec, "name": "measured"}, headers=acc.headers)
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["n_cells"] == parse_spec(spec).n_cells == 2 * 3 * 2
    assert job["spec"]["dataset"] == ds["id"] and job["spec"]["sigma_w"] == "estimate"
    assert run_worker_units(session, scope, job["id"]) == job["progress"]["total"]
    done = client.get(f"{API}/jobs/{job['id']}", headers=acc.headers).json()
    assert done["status"] == "succeeded" and done["cells_done"] == job["n_cells"]
    got = rest_records(client, acc, job["id"])
    assert_same(got, in_process(spec, X, U))
    rec = got[(f"dataset-{ds['id']}", -1.0, 12, "ols", -1.0, 0)]
    assert rec["rmse_A"] is None and "measured data: no true system" in rec["notes"]
    assert np.abs(np.array(rec["A_hat"]) - A_TRUE).max() < 0.2  # the estimate is near the truth
    summary = client.get(f"{API}/jobs/{job['id']}/summary", headers=acc.headers).json()
    assert {(g["N"], g["estimator"]) for g in summary["groups"]} == {
        (N, e) for N in (6, 12) for e in ("ols", "svr")
    }
    assert all(g["count"] == 3 for g in summary["groups"])

    # the validation: stored by the worker after the first unit, served as stored
    assert session.scalar(select(func.count()).select_from(JobValidation)) >= 1
    body = client.get(f"{API}/jobs/{job['id']}/validation", headers=acc.headers)
    assert body.status_code == 200, body.text
    want = summarize(job["spec"], MeasuredData(X=X, U=U))
    got_v = body.json()
    assert got_v.pop("job_id") == job["id"] and got_v.pop("dataset") == ds["id"]
    assert not same(got_v, json.loads(json.dumps(want, allow_nan=False)))
    assert len(got_v["models"]) == 2 and got_v["N"] == 12 and got_v["holdout"] == 3
    v = got_v["models"][0]["validation"]
    assert len(v["predicted"]) == len(got_v["plots"]["measured"]) == min(3, PLOTTED_ROLLOUTS)
    assert np.array(got_v["plots"]["measured"][0]).shape == (31, 3)
    assert np.array(v["predicted"][0]).shape == (30, 3)
    assert len(v["autocorrelation"][0]) == v["lags"] and v["band"] > 0

    # the report of a dataset job: built, truth fields null with their reason
    report = client.get(f"{API}/jobs/{job['id']}/report", headers=acc.headers)
    assert report.status_code == 200 and "measured data: no true system" in report.text


def test_the_stored_validation_keeps_a_plots_worth_of_series_and_every_statistic():
    """Long held-out rollouts: what is stored keeps the per-step series of the first
    PLOTTED_ROLLOUTS rollouts and their first ``steps`` steps only (at most
    PLOTTED_VALUES numbers), and every statistic is the one of all held-out steps
    (``validation_summary`` uncut)."""
    X, U = simulate(13, rollouts=9, T=20_000)
    data = MeasuredData(X=X, U=U)
    spec = {**SPEC, "dataset": 1, "N": [1, 2], "holdout": 7, "gamma": [0.01, 0.05, 0.1]}
    got = summarize(spec, data)
    whole = validation_summary(parse_spec(spec), data)
    steps = got["plots"]["steps"]
    assert got["plots"]["cut"] and 1 <= steps < 20_000
    assert got["plots"]["rollouts"] == list(range(2, 2 + PLOTTED_ROLLOUTS))
    numbers = 3 * len(got["plots"]["measured"]) * len(got["plots"]["measured"][0])
    for cut, full in zip(got["models"], whole["models"]):
        v, w = cut["validation"], full["validation"]
        assert len(v["predicted"]) == len(v["simulated"]) == PLOTTED_ROLLOUTS
        for r in range(PLOTTED_ROLLOUTS):
            assert v["predicted"][r] == w["predicted"][r][:steps]
            assert v["simulated"][r] == w["simulated"][r][: steps + 1]
            assert np.array(got["plots"]["measured"][r]) == pytest.approx(X[2 + r][: steps + 1])
        numbers += sum(3 * (len(p) + len(q)) for p, q in zip(v["predicted"], v["simulated"]))
        assert len(w["simulated"]) == 7 and len(w["simulated"][0]) == 20_001
        stats = {k: x for k, x in w.items() if k not in ("predicted", "simulated")}
        assert {k: v[k] for k in stats} == stats
    assert numbers <= PLOTTED_VALUES


def test_a_validation_computed_on_request_holds_no_connection_and_counts_as_a_build(
    build_client, session_factory, make_account, monkeypatch
):
    """A validation the API computes (the job's units never ran) takes up to the job's
    own CPU time (seconds per thousand gamma values): no session of the request is in
    a transaction meanwhile (each held a pooled connection: fifteen such requests took
    PostgreSQL's pool from every other team), and it is one of the team's report
    builds, under SVROBS_REPORT_BUILDS_PER_TEAM (429 with Retry-After beyond)."""
    from svrobs_lab import validation

    client, _ = build_client(REPORT_BUILDS_PER_TEAM=1)
    opened = track_sessions(client.app, session_factory)
    in_transaction: list[bool] = []

    def watched(spec, data):
        in_transaction.append(any(s.in_transaction() for s in opened))
        return summarize(spec, data)

    monkeypatch.setattr(validation, "summarize", watched)
    acc = make_account()
    X, U = simulate(5, rollouts=8, T=25)
    ds = upload(client, acc, "d.npz", files.npz_bytes(X, U))
    spec = {"dataset": ds["id"], "N": [5], "holdout": 2, "reps": 1, "sigma_w": 0.2}
    first, second = (
        client.post(f"{API}/jobs", json={**spec, "seed": seed}, headers=acc.headers).json()["id"]
        for seed in (1, 2)
    )
    r = client.get(f"{API}/jobs/{first}/validation", headers=acc.headers)
    assert r.status_code == 200 and r.json()["job_id"] == first, r.text
    assert in_transaction == [False]
    builds = client.app.state.report_builds
    builds._building[acc.team.id] += 1  # the team's one build (a report) in progress
    busy = client.get(f"{API}/jobs/{second}/validation", headers=acc.headers)
    assert busy.status_code == 429 and int(busy.headers["retry-after"]) >= 1, busy.text
    assert client.get(f"{API}/jobs/{first}/validation", headers=acc.headers).json() == r.json()
    builds._building[acc.team.id] -= 1
    assert client.get(f"{API}/jobs/{second}/validation", headers=acc.headers).status_code == 200
    assert in_transaction == [False, False]


def test_no_inputs_gives_n_by_zero_matrices_and_the_validation_is_computed_once(
    client, session, scope, make_account
):
    """m = 0 (an autonomous system): B_hat and radii_B are n x 0 through the store;
    a job whose units never ran gets its validation computed by the API, once."""
    acc = make_account()
    X, U = simulate(5, rollouts=8, T=25, m=0)
    ds = upload(client, acc, "free.npz", files.npz_bytes(X, U))
    assert ds["m"] == 0
    spec = {"dataset": ds["id"], "N": [5], "holdout": 2, "reps": 2, "sigma_w": 0.2, "seed": 1}
    job = client.post(f"{API}/jobs", json=spec, headers=acc.headers).json()
    first = client.get(f"{API}/jobs/{job['id']}/validation", headers=acc.headers)
    assert first.status_code == 200, first.text
    again = client.get(f"{API}/jobs/{job['id']}/validation", headers=acc.headers)
    assert again.json() == first.json()
    rows = select(func.count()).select_from(JobValidation).where(JobValidation.job_id == job["id"])
    assert session.scalar(rows) == 1
    assert first.json()["models"][0]["B_hat"] == [[], [], []]
    run_worker_units(session, scope, job["id"])
    got = rest_records(client, acc, job["id"])
    assert_same(got, in_process(spec, X, U))
    assert all(r["B_hat"] == [[], [], []] for r in got.values())
    assert all(r["radii_B"] in ([[], [], []], None) for r in got.values())
    # a simulated job has no validation
    sim = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()
    r = client.get(f"{API}/jobs/{sim['id']}/validation", headers=acc.headers)
    assert r.status_code == 404 and "not on a dataset" in r.json()["detail"]
    other = make_account()
    r = client.get(f"{API}/jobs/{job['id']}/validation", headers=other.headers)
    assert r.status_code == 404


def test_submit_checks_a_dataset_spec_against_the_teams_dataset(client, make_account):
    acc, other = make_account(), make_account()
    X, U = simulate(2, rollouts=4, T=10)
    ds = upload(client, acc, "p.csv", files.csv_bytes(X, U))
    base = {"dataset": ds["id"], "N": [2], "holdout": 1, "reps": 1}
    cases = [
        ({**base, "N": [4]}, "N", "the dataset has 3 for training"),
        ({**base, "holdout": 4}, "holdout", "below the dataset's 4 rollouts"),
        ({**base, "C": [[1, 0]]}, "C", "must have 3 columns"),
        ({**base, "systems": ["paper-stable"]}, "dataset", "not both"),
        ({**base, "T0": 5}, "T0", "describes a simulation"),
        ({**base, "sigma_w": "guess"}, "sigma_w", '"estimate"'),
        ({**base, "dataset": True}, "dataset", "integer"),
        ({**base, "bounds_method": "bootstrap"}, "bounds_method", "the bootstrap re-simulates"),
        ({**base, "bounds_method": "paper"}, "bounds_method", 'must be "self-normalized"'),
        ({**base, "boot_reps": 50}, "boot_reps", "is not used with a dataset"),
    ]
    for spec, field, text in cases:
        r = client.post(f"{API}/jobs", json=spec, headers=acc.headers)
        assert r.status_code == 422 and r.json()["field"] == field, (spec, r.text)
        assert text in r.json()["detail"], r.json()
    r = client.post(f"{API}/jobs", json=base, headers=other.headers)
    assert r.status_code == 422 and r.json() == {
        "detail": f"no dataset {ds['id']} in your team",
        "field": "dataset",
    }
    assert client.post(f"{API}/jobs", json=base, headers=acc.headers).status_code == 202


def test_limits_and_the_memory_cap_apply_to_dataset_jobs(build_client, make_account, session):
    acc = make_account()
    X, U = simulate(3, rollouts=30, T=40)
    client, _ = build_client(MAX_JOB_CPU_SECONDS=1.0, MAX_UNIT_MEMORY_MB=60)
    ds = upload(client, acc, "p.csv", files.csv_bytes(X, U))
    big = {"dataset": ds["id"], "N": [10, 20, 28], "holdout": 2, "reps": 400, "gamma": [0.1]}
    big["stages"] = ["estimate", "bounds", "gain", "cost"]
    r = client.post(f"{API}/jobs", json=big, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "reps", r.text
    assert "SVROBS_MAX_JOB_CPU_SECONDS" in r.json()["detail"]
    # under a memory cap a little above the fixed bytes, units hold fewer repetitions
    ok = {"dataset": ds["id"], "N": [28], "holdout": 2, "reps": 8}
    loose, _ = build_client(MAX_UNIT_MEMORY_MB=2048)
    tight, _ = build_client(MAX_UNIT_MEMORY_MB=51)
    j1 = loose.post(f"{API}/jobs", json=ok, headers=acc.headers).json()
    j2 = tight.post(f"{API}/jobs", json=ok, headers=acc.headers)
    assert j2.status_code == 202, j2.text
    j2 = j2.json()
    assert j1["progress"]["total"] == 1 < j2["progress"]["total"]
    payloads = session.scalars(
        select(WorkUnit.payload).where(WorkUnit.job_id == j2["id"]).order_by(WorkUnit.index)
    ).all()
    covered = [r for p in payloads for r in range(*p["reps"])]
    assert covered == list(range(8))
    small, _ = build_client(MAX_UNIT_MEMORY_MB=10)
    r = small.post(f"{API}/jobs", json=ok, headers=acc.headers)
    assert r.status_code == 422 and "SVROBS_MAX_UNIT_MEMORY_MB" in r.json()["detail"]


def test_schedules_take_dataset_specs_checked_at_creation(client, make_account):
    acc, other = make_account(), make_account()
    X, U = simulate(8, rollouts=5, T=12)
    ds = upload(client, acc, "p.csv", files.csv_bytes(X, U))
    template = {"dataset": ds["id"], "N": [2, 4], "holdout": 1, "reps": 2}
    body = {"name": "nightly-fit", "cron": "0 3 * * *", "spec_template": template}
    r = client.post(f"{API}/schedules", json=body, headers=acc.headers)
    assert r.status_code == 201, r.text
    bad = {**body, "name": "too-many", "spec_template": {**template, "N": [5]}}
    r = client.post(f"{API}/schedules", json=bad, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "spec_template.N"
    r = client.post(f"{API}/schedules", json={**body, "name": "theirs"}, headers=other.headers)
    assert r.status_code == 422 and r.json()["field"] == "spec_template.dataset"
    sid = client.get(f"{API}/schedules", headers=acc.headers).json()[0]["id"]
    r = client.patch(
        f"{API}/schedules/{sid}",
        json={"spec_template": {**template, "holdout": 5}},
        headers=acc.headers,
    )
    assert r.status_code == 422 and r.json()["field"] == "spec_template.holdout"


def test_a_dataset_jobs_failed_unit_names_the_dataset(session, make_account, client):
    acc = make_account()
    X, U = simulate(1, rollouts=4, T=10)
    ds = upload(client, acc, "p.csv", files.csv_bytes(X, U))
    job, _ = job_store.create_job(
        session, team_id=acc.team.id, user_id=None, spec={"dataset": ds["id"], "N": [2], "reps": 1}
    )
    session.commit()
    (uid,) = job_store.unit_ids_of_job(session, job.id)
    units.start_unit(session, uid, "w1", 60, max_attempts=0)
    units.fail_unit(session, uid, "ValueError: boom", True)
    session.commit()
    failed = client.get(f"{API}/jobs/{job.id}", headers=acc.headers).json()
    assert failed["status"] == "failed"
    assert failed["error"].startswith(f"unit 0 (system=dataset-{ds['id']}, sigma_w=estimate, N=[2]")


@pytest.fixture
def deleted_after_check(monkeypatch, session_factory):
    """create_job's dataset check, then the dataset deleted and committed by another
    session before the job's insert (which the foreign key on jobs.dataset_id refuses;
    SQLite enforces it too: PRAGMA foreign_keys). The other session's delete_dataset
    found no schedule naming it (one made meanwhile, in the schedule's case). The
    sessions share the test's connection, so the request's rollback also undoes that
    delete."""
    check = job_store.spec_data

    def then_deleted(session, team_id, spec, field="dataset"):
        out = check(session, team_id, spec, field)
        with session_factory() as other, monkeypatch.context() as m:
            row = dataset_store.team_dataset(other, team_id, out[0])
            assert row is not None
            m.setattr(dataset_store, "schedules_naming", lambda *args: [])
            dataset_store.delete_dataset(other, row)
            other.commit()
        return out

    monkeypatch.setattr(job_store, "spec_data", then_deleted)


def _jobs_on(session, dataset_id: int) -> int:
    session.expire_all()
    return session.scalar(select(func.count(Job.id)).where(Job.dataset_id == dataset_id))


def test_a_dataset_deleted_while_its_job_is_submitted_is_the_422_of_a_missing_one(
    client, session, make_account, deleted_after_check
):
    acc = make_account()
    X, U = simulate(5, rollouts=4, T=10)
    ds = upload(client, acc, "p.csv", files.csv_bytes(X, U))
    spec = {"dataset": ds["id"], "N": [2], "holdout": 1, "reps": 1}
    r = client.post(f"{API}/jobs", json=spec, headers=acc.headers)
    assert r.status_code == 422, r.text
    assert r.json() == {"detail": f"no dataset {ds['id']} in your team", "field": "dataset"}
    assert _jobs_on(session, ds["id"]) == 0


def test_a_dataset_deleted_while_its_schedule_runs_is_that_runs_error(
    client, session, make_account, deleted_after_check
):
    """The tick records the missing dataset on the run, as for any spec error, and goes on."""
    acc = make_account()
    X, U = simulate(6, rollouts=4, T=10)
    ds = upload(client, acc, "p.csv", files.csv_bytes(X, U))
    sched = Schedule(
        team_id=acc.team.id,
        user_id=acc.user.id,
        name="nightly-fit",
        cron="0 2 * * *",
        timezone="UTC",
        spec_template={"dataset": ds["id"], "N": [2], "holdout": 1, "reps": 1},
        tags=[],
        created_at=datetime(2024, 1, 1, tzinfo=UTC),
    )
    session.add(sched)
    session.commit()
    made = lab_schedules.create_due_jobs(
        get_settings(), session, datetime(2024, 6, 1, 3, tzinfo=UTC)
    )
    session.commit()
    assert not [j for j in made if j.team_id == acc.team.id]
    run = session.scalar(select(ScheduleRun).where(ScheduleRun.schedule_id == sched.id))
    assert run is not None and run.job_id is None
    assert run.error == f"dataset: no dataset {ds['id']} in your team"
    assert _jobs_on(session, ds["id"]) == 0


def test_a_job_that_holds_no_rollout_out_has_its_validation_stored(
    client, session, scope, make_account, caplog
):
    """holdout 0: the worker stores the validation (no model is validated, the
    excitation check is there, nothing to plot) and the API serves it."""
    acc = make_account()
    X, U = simulate(12, rollouts=12, T=20)
    ds = upload(client, acc, "all-in.csv", files.csv_bytes(X, U))
    spec = {**SPEC, "dataset": ds["id"], "holdout": 0}
    job = client.post(f"{API}/jobs", json=spec, headers=acc.headers).json()
    with caplog.at_level("WARNING", logger="svrobs_lab.units"):
        run_worker_units(session, scope, job["id"])
    assert not [m for m in caplog.messages if "validation failed" in m], caplog.messages
    stored = session.scalar(
        select(func.count()).select_from(JobValidation).where(JobValidation.job_id == job["id"])
    )
    assert stored == 1
    body = client.get(f"{API}/jobs/{job['id']}/validation", headers=acc.headers)
    assert body.status_code == 200, body.text
    got = body.json()
    assert got["holdout"] == 0 and got["plots"]["rollouts"] == [] and got["plots"]["measured"] == []
    assert [m["validation"] for m in got["models"]] == [None, None]
    want = summarize(job["spec"], MeasuredData(X=X, U=U))
    assert got["models"] == json.loads(json.dumps(want["models"], allow_nan=False))
