"""Retention: a team's scheduled jobs lose their cell rows K days
after they finished; summary, compare by group fields and the report keep working,
the results routes answer 410. Oracles: the summary, compare and report of the
same job before pruning (the report from its records decoded row by row)."""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import func, select

from service.db.clock import db_now
from service.db.models import Job, JobReport, Result, Schedule
from service.db.results_store import load_records
from service.db.retention import set_retention
from svrobs_lab.report_html import job_report_html
from tests.service.svc_fakes import run_job_units
from tests.service.svc_helpers import SMALL_SPEC, scope_of
from tests.web.helpers import sign_in
from worker.tick import prune_expired

API = "/api/v1"


def _finished_job(client, session, acc, *, scheduled: bool, days_ago: float) -> int:
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    run_job_units(session, jid)
    job = session.get(Job, jid)
    if scheduled:
        sched = Schedule(
            team_id=acc.team.id, name=f"nightly-{jid}", cron="0 3 * * *", spec_template=SMALL_SPEC
        )
        session.add(sched)
        session.flush()
        job.schedule_id = sched.id
    job.finished_at = db_now(session) - timedelta(days=days_ago)
    session.commit()
    return jid


def _rows(session, jid) -> int:
    return session.scalar(select(func.count()).select_from(Result).where(Result.job_id == jid))


def test_retention_prunes_due_scheduled_jobs_only_and_reads_keep_working(
    client, session, session_factory, make_account
):
    acc, other = make_account(), make_account()
    due = _finished_job(client, session, acc, scheduled=True, days_ago=3)
    young = _finished_job(client, session, acc, scheduled=True, days_ago=1)
    manual = _finished_job(client, session, acc, scheduled=False, days_ago=30)
    off = _finished_job(client, session, other, scheduled=True, days_ago=30)  # retention off
    set_retention(session, acc.team.id, 2)
    session.commit()

    def get(path, **params):
        return client.get(f"{API}{path}", params=params, headers=acc.headers)

    summary = get(f"/jobs/{due}/summary").json()
    by_group = {"jobs": due, "metric": "rmse_A", "by": "system,sigma_w,N,estimator,gamma"}
    compared = get("/compare", **by_group).json()
    records = load_records(session, due)
    job = get(f"/jobs/{due}").json()

    assert prune_expired(scope=scope_of(session_factory)) == [due]
    session.expire_all()
    assert _rows(session, due) == 0
    assert all(_rows(session, j) > 0 for j in (young, manual, off))
    assert get(f"/jobs/{due}").json()["pruned_at"] is not None
    assert get(f"/jobs/{young}").json()["pruned_at"] is None
    for fmt in ("json", "csv", "jsonl"):
        r = get(f"/jobs/{due}/results", format=fmt)
        assert r.status_code == 410, r.text
        assert "retention" in r.json()["detail"] and r.headers["content-type"].startswith(
            "application/json"
        )
    sign_in(client, acc.key)  # the results page and its grid say it too
    for path in (f"/results?job={due}", f"/results/rows?job={due}"):
        r = client.get(path)
        assert r.status_code == 410 and "retention" in r.text, path
    assert get(f"/jobs/{due}/summary").json() == summary
    assert get("/compare", **by_group).json() == compared
    r = get("/compare", **{**by_group, "by": "N,rep"})
    assert r.status_code == 410 and r.json()["field"] == "by"
    # the report was stored before the rows went, from those rows
    stored = session.get(JobReport, due)
    assert stored is not None and stored.n_records == len(records)
    page = get(f"/jobs/{due}/report")
    assert page.status_code == 200 and page.text == stored.html
    provenance = {
        **job["provenance"],
        "job_id": due,
        "status": "succeeded",
        "progress": f"{job['progress']['done']}/{job['progress']['total']} units",
    }
    records.sort(
        key=lambda x: (
            x["system"],
            x["sigma_w"],
            x["N"],
            x["estimator"],
            -1 if x["gamma"] is None else x["gamma"],
            x["rep"],
        )
    )
    assert page.text == job_report_html(job["spec"], records, provenance, name=f"job-{due}")
    assert prune_expired(scope=scope_of(session_factory)) == []  # nothing left to do

    set_retention(session, acc.team.id, None)  # off again: nothing more is pruned
    session.get(Job, young).finished_at = db_now(session) - timedelta(days=10)
    session.commit()
    assert prune_expired(scope=scope_of(session_factory)) == []
