"""Bounded reads: the report read as columns and stored once,
compare aggregated in the database and paginated, GET /jobs with a spec summary.

Oracles: the report built from the records decoded row by row
(``load_records``, every record decoded); compare numbers from numpy over
those records; the spec summary from the spec itself."""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np
import pytest
from sqlalchemy import delete

from service.db.models import JobReport, Result
from service.db.reports import load_columns
from service.db.result_blocks import drop_blocks
from service.db.results_store import load_records
from svrobs_core.parsing import parse_spec
from svrobs_core.report import Columns
from svrobs_core.runner import run_unit
from svrobs_lab.report_html import job_report_html
from tests.service.svc_fakes import run_job_units
from tests.service.svc_helpers import SMALL_SPEC, scope_of

API = "/api/v1"
REAL_SPEC = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.1, 1.0],
    "N": [20, 40],
    "reps": 3,
    "gamma": [0.05, 0.1],
    "estimators": ["ols", "svr"],
    "stages": ["estimate", "bounds", "gain"],
    "seed": 5,
}


def _records(session, job_id) -> list[dict]:
    return load_records(session, job_id)  # in grid order


def _run_core(session, job_id):
    from service.db import jobs, units

    for uid in jobs.unit_ids_of_job(session, job_id, pending_only=False):
        spec, payload = units.start_unit(session, uid, "test", 60, max_attempts=0)
        units.complete_unit(session, uid, run_unit(parse_spec(spec), payload))
        session.commit()


def _same_columns(a: Columns, b: Columns):
    assert a.n == b.n and set(a.data) == set(b.data)
    for f in a.data:
        x, y = a.data[f], b.data[f]
        if x.dtype == object:
            assert list(x) == list(y), f
            # the codes the reader factorised as it read are the ones codes() computes
            (cx, vx), (cy, vy) = a.codes(f), b.codes(f)
            assert vx == vy and cx.tolist() == cy.tolist(), f
        else:
            np.testing.assert_array_equal(x, y, err_msg=f)  # NaN == NaN here


def test_report_from_columns_equals_report_from_rows_and_is_stored(client, session, make_account):
    acc = make_account()
    jid = client.post(f"{API}/jobs", json={**REAL_SPEC, "name": "r"}, headers=acc.headers).json()[
        "id"
    ]
    _run_core(session, jid)
    records = _records(session, jid)
    _same_columns(load_columns(session, jid), Columns.from_records(records))
    r = client.get(f"{API}/jobs/{jid}/report", headers=acc.headers)
    assert r.status_code == 200, r.text
    job = client.get(f"{API}/jobs/{jid}", headers=acc.headers).json()
    provenance = {
        **job["provenance"],
        "job_id": jid,
        "status": "succeeded",
        "progress": f"{job['progress']['done']}/{job['progress']['total']} units",
    }
    assert r.text == job_report_html(job["spec"], records, provenance, name="r")
    stored = session.get(JobReport, jid)
    assert stored is not None and stored.n_records == len(records) and stored.html == r.text
    # a finished job's report is served as stored: it no longer reads the rows
    session.execute(delete(Result).where(Result.job_id == jid))
    session.commit()
    again = client.get(f"{API}/jobs/{jid}/report", headers=acc.headers)
    assert again.status_code == 200 and again.text == r.text


def test_load_columns_without_matrices_and_running_job_report_not_stored(
    client, session, make_account
):
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    run_job_units(session, jid, count=1)
    cols = load_columns(session, jid, matrices=False)
    assert "A_hat" not in cols.data and cols.n == len(_records(session, jid)) > 0
    full = Columns.from_records(_records(session, jid), matrices=False)
    _same_columns(cols, full)
    r = client.get(f"{API}/jobs/{jid}/report", headers=acc.headers)
    assert r.status_code == 200 and "<html lang=" in r.text
    assert session.get(JobReport, jid) is None  # a running job changes: never stored


def _finished_fake_job(
    client, session, make_account, spec=SMALL_SPEC, *, make=None
) -> tuple[int, list[dict]]:
    """A job of fake records (``make(spec, payload)``, default ``fake_records``) whose
    units were stored last first (so the rows' storage order is not the grid's)."""
    from service.db import jobs, units
    from tests.service.svc_fakes import fake_records

    make = make or fake_records

    acc = make_account()
    r = client.post(f"{API}/jobs", json=spec, headers=acc.headers)
    assert r.status_code == 202, r.text
    jid = r.json()["id"]
    for uid in reversed(jobs.unit_ids_of_job(session, jid, pending_only=False)):
        spec, payload = units.start_unit(session, uid, "w", 60, max_attempts=0)
        units.complete_unit(session, uid, make(spec, payload))
        session.commit()
    return jid, _records(session, jid)


@pytest.mark.parametrize("block", [None, 7], ids=["blocks of 4 MB", "blocks of 7 bytes"])
def test_postgresql_reads_report_columns_by_one_copy(
    client, session, make_account, monkeypatch, block
):
    """On PostgreSQL the columns come from the binary COPY (the row read is not used)
    and equal the records': floats, NaN for null, booleans, notes and their codes;
    also when the stream is parsed in pieces that split its header and rows."""
    if session.get_bind().dialect.name != "postgresql":
        pytest.skip("the COPY read is PostgreSQL's")
    from service.db import report_copy, reports

    if block is not None:
        monkeypatch.setattr(report_copy, "_BLOCK", block)

    jid, records = _finished_fake_job(client, session, make_account)
    assert any(r["notes"] for r in records) and any(r["notes"] is None for r in records)
    drop_blocks(session, jid)  # else they are read: see test_service_result_blocks

    def no_rows(*a, **k):
        raise AssertionError("the row read was used")

    monkeypatch.setattr(reports, "_chunks", no_rows)
    # a sequential scan: the rows come in their storage order (last unit first)
    from sqlalchemy import text

    session.execute(text("SET LOCAL enable_indexscan = off"))
    session.execute(text("SET LOCAL enable_bitmapscan = off"))
    _same_columns(
        load_columns(session, jid, matrices=False), Columns.from_records(records, matrices=False)
    )


def test_copy_read_quotes_and_orders_system_names_as_the_database(
    client, session, make_account, monkeypatch
):
    """System names with quotes, a backslash, non-ASCII letters and both cases: the
    COPY's CASE literals match them, and the rows come in the database's order of
    them (as the row read's ORDER BY gives it)."""
    if session.get_bind().dialect.name != "postgresql":
        pytest.skip("the COPY read is PostgreSQL's")
    from service.db import reports
    from svrobs_core.systems import resolve_system

    paper = resolve_system("paper-stable")
    names = ["Zeta 'q' \\ ü", 'alpha "x" É', "Émile;--"]
    systems = [{"name": n, "A": paper.A.tolist(), "B": paper.B.tolist()} for n in names]
    jid, records = _finished_fake_job(
        client, session, make_account, {**SMALL_SPEC, "systems": systems}
    )
    assert {r["system"] for r in records} == set(names)
    drop_blocks(session, jid)
    monkeypatch.setattr(reports, "_chunks", lambda *a, **k: pytest.fail("the row read was used"))
    _same_columns(
        load_columns(session, jid, matrices=False), Columns.from_records(records, matrices=False)
    )


def test_copy_read_falls_back_to_rows_when_a_value_is_new(
    client, session, make_account, monkeypatch, caplog
):
    """A text value the distinct read did not see (a running job's new rows): the
    whole COPY stream is still read, and the rows are read instead, in the same
    transaction."""
    if session.get_bind().dialect.name != "postgresql":
        pytest.skip("the COPY read is PostgreSQL's")
    from service.db import report_copy

    jid, records = _finished_fake_job(client, session, make_account)
    seen = report_copy._distinct

    def without_svr(s, job_id):
        d = seen(s, job_id)
        return {**d, "estimator": [v for v in d["estimator"] if v != "svr"]}

    monkeypatch.setattr(report_copy, "_distinct", without_svr)
    drop_blocks(session, jid)
    with caplog.at_level("INFO", logger="service.db.reports"):
        cols = load_columns(session, jid, matrices=False)
    assert "reading rows" in caplog.text
    _same_columns(cols, Columns.from_records(records, matrices=False))


def test_copy_read_of_more_rows_than_counted_reads_the_rows_instead(client, session, make_account):
    """A running job that stored rows after they were counted: the COPY (no ORDER
    BY) would hand over another set than the row read's first rows, so it stops."""
    if session.get_bind().dialect.name != "postgresql":
        pytest.skip("the COPY read is PostgreSQL's")
    from service.db.report_copy import StreamChanged, copy_columns

    jid, records = _finished_fake_job(client, session, make_account)
    data, _ = copy_columns(session, jid, len(records))
    assert len(data["rep"]) == len(records)
    with pytest.raises(StreamChanged):
        copy_columns(session, jid, len(records) - 1)


def test_column_read_notes_of_more_ids_than_a_statement_has_parameters(session):
    """The notes' texts are read with the ids as one array parameter on PostgreSQL
    (at most 65,535 parameters in a statement), in lists of 500 on SQLite; unknown
    ids and -1 are None."""
    from service.db.report_order import _notes
    from service.db.results_store import note_ids

    stored = note_ids(session, ["first note", "second note"])
    a, b = stored["first note"], stored["second note"]
    unknown = np.arange(10**6, 10**6 + 70_000)
    ids = np.concatenate([[b, -1], unknown, [a, b]]).astype(np.int64)
    codes, values = _notes(session, ids)
    assert values == ["second note", None, "first note"]
    assert codes.tolist() == [0, 1] + [1] * unknown.size + [2, 0]


def test_a_driver_error_in_the_copy_read_is_reported_as_sqlalchemy_reports_it(session, monkeypatch):
    """An error of the COPY (psycopg's) comes out as SQLAlchemy's DBAPIError, as the
    row read's would (the API maps those to 503 once)."""
    if session.get_bind().dialect.name != "postgresql":
        pytest.skip("the COPY read is PostgreSQL's")
    from psycopg import sql
    from sqlalchemy.exc import ProgrammingError

    from service.db import report_copy

    bad = sql.SQL("COPY (SELECT 1 FROM no_such_table) TO STDOUT (FORMAT BINARY)")
    monkeypatch.setattr(report_copy, "_copy_sql", lambda *a: (bad, 1))
    with pytest.raises(ProgrammingError, match="no_such_table"):
        report_copy.copy_columns(session, 1, 10)


def _two_finished_jobs(client, session, acc) -> tuple[int, int]:
    """Two finished jobs, the second finished last (the first a report poll takes)."""
    ids = [
        client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
        for _ in range(2)
    ]
    for jid in ids:
        run_job_units(session, jid)
    session.commit()
    return ids[0], ids[1]


def test_a_failing_report_build_holds_up_neither_other_jobs_nor_the_log(
    client, session, session_factory, make_account, monkeypatch, caplog
):
    """Beat's report builds: a job whose build fails is logged once, skipped for
    REPORT_RETRY_SECONDS while the others are built, and then tried again."""
    import svrobs_lab.reports as lab_reports
    from worker import tick

    good, bad = _two_finished_jobs(client, session, make_account())  # bad: first in line
    real, tried = lab_reports.store_if_missing, []

    def failing(r, w, job_id, **kw):
        tried.append(job_id)
        if job_id == bad:
            raise ValueError("a report that cannot be built")
        return real(r, w, job_id, **kw)

    monkeypatch.setattr(lab_reports, "store_if_missing", failing)
    monkeypatch.setattr(tick, "_failed_reports", {})
    scope = scope_of(session_factory)
    with caplog.at_level("ERROR", logger="worker.tick"):
        assert tick.build_reports(limit=1, scope=scope) == []  # only the bad one fits
        assert tick.build_reports(limit=1, scope=scope) == [good]  # the bad one is skipped
        assert tick.build_reports(limit=1, scope=scope) == []
    failures = [r for r in caplog.records if r.getMessage().startswith("tick: the report of job")]
    assert tried == [bad, good] and len(failures) == 1
    tick._failed_reports[bad] -= tick.REPORT_RETRY_SECONDS  # its pause is over
    assert tick.build_reports(limit=1, scope=scope) == [] and tried[-1] == bad


def test_a_database_error_in_a_report_build_is_not_held_against_the_job(
    client, session, session_factory, make_account, monkeypatch
):
    """The database lost during a build is raised (the report thread warns and polls
    again); the job is not set aside as one whose report cannot be built."""
    from sqlalchemy.exc import OperationalError

    import svrobs_lab.reports as lab_reports
    from worker import tick

    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    run_job_units(session, jid)
    session.commit()

    def down(r, w, job_id, **_):
        raise OperationalError(
            "SELECT 1", {}, Exception("server closed the connection"), connection_invalidated=True
        )

    monkeypatch.setattr(lab_reports, "store_if_missing", down)
    monkeypatch.setattr(tick, "_failed_reports", {})
    with pytest.raises(OperationalError):
        tick.build_reports(limit=1, scope=scope_of(session_factory))
    assert tick._failed_reports == {}


def test_a_database_error_of_one_job_with_the_database_up_sets_that_job_aside(
    client, session, session_factory, make_account, monkeypatch, caplog
):
    """A database error of one job's build (a statement or idle-in-transaction timeout
    on its read) while the database answers is that job's failure: it is logged with
    its id and set aside, and the other jobs are built."""
    from sqlalchemy.exc import OperationalError

    import svrobs_lab.reports as lab_reports
    from worker import tick

    good, bad = _two_finished_jobs(client, session, make_account())  # bad: first in line
    real = lab_reports.store_if_missing

    def timing_out(r, w, job_id, **kw):
        if job_id == bad:
            raise OperationalError("SELECT ...", {}, Exception("canceling statement"))
        return real(r, w, job_id, **kw)

    monkeypatch.setattr(lab_reports, "store_if_missing", timing_out)
    monkeypatch.setattr(tick, "_failed_reports", {})
    with caplog.at_level("ERROR", logger="worker.tick"):
        assert tick.build_reports(limit=2, scope=scope_of(session_factory)) == [good]
    assert list(tick._failed_reports) == [bad]
    assert any(f"report of job {bad} failed" in r.getMessage() for r in caplog.records)


def test_the_read_transaction_is_ended_before_the_report_renders(
    client, session, session_factory, make_account, monkeypatch
):
    """A background build reads the rows, ends its read transaction, then renders: no
    transaction stays open for the seconds of a large report's figures (a server's
    idle-in-transaction timeout would end it, and on SQLite it pins the WAL)."""
    import svrobs_lab.reports as lab_reports

    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    run_job_units(session, jid)
    session.commit()
    scope, open_while_rendering = scope_of(session_factory), []
    real_render = lab_reports._render_columns
    with scope(write=False) as r, scope(write=True) as w:

        def render(*a):
            open_while_rendering.append(r.in_transaction())
            return real_render(*a)

        monkeypatch.setattr(lab_reports, "_render_columns", render)
        assert lab_reports.store_if_missing(r, w, jid)
    assert open_while_rendering == [False]


def test_once_stopping_no_build_starts_and_none_renders_after_its_read(
    client, session, session_factory, make_account, monkeypatch
):
    """At exit the report thread neither starts the next job's build nor renders the
    one whose rows it was reading: nothing is stored, and it ends at once."""
    import threading

    import svrobs_lab.reports as lab_reports
    from service.db.reports import stored_report
    from worker import tick

    first, second = _two_finished_jobs(client, session, make_account())
    stop, tried, rendered = threading.Event(), [], []
    real_read, real_render = lab_reports._read_rows, lab_reports._render_columns

    def read_then_stop(s, job_id):  # the process is told to stop during the read
        tried.append(job_id)
        cols = real_read(s, job_id)
        stop.set()
        return cols

    def render(*a):
        rendered.append(1)
        return real_render(*a)

    monkeypatch.setattr(lab_reports, "_read_rows", read_then_stop)
    monkeypatch.setattr(lab_reports, "_render_columns", render)
    monkeypatch.setattr(tick, "_stop_reports", stop)
    monkeypatch.setattr(tick, "_failed_reports", {})
    assert tick.build_reports(limit=2, scope=scope_of(session_factory)) == []
    assert len(tried) == 1 and rendered == []
    session.expire_all()
    assert stored_report(session, first) is None and stored_report(session, second) is None


def _numpy_compare(records, jid, metric, by):
    values, seen = defaultdict(list), set()
    for rec in records:
        key = (jid, *(rec[b] for b in by))
        seen.add(key)
        v = rec[metric]
        if v is not None and math.isfinite(float(v)):
            values[key].append(float(v))
    out = {}
    for key in seen:
        v = np.array(values.get(key, []))
        out[key] = (v.mean() if v.size else None, v.std() if v.size else None, v.size)
    return out


@pytest.mark.parametrize(
    "metric,by",
    [
        ("rmse_A", "N,estimator,gamma"),  # from the summaries
        ("thm1_holds_A", "system,sigma_w,N,estimator,gamma"),  # booleans, summaries
        ("rmse_B", "estimator"),  # all null
        ("H_A", "N,rep"),  # rep: from the rows
        ("rmse_A", "rep,gamma,N,system,estimator,sigma_w"),  # the cell key: one row a group
        ("thm1_holds_A", "system,sigma_w,N,N0,estimator,gamma,rep"),
        ("N0", "gamma"),  # not a summary field: from the rows
    ],
)
def test_compare_in_the_database_equals_numpy_over_the_rows(
    client, session, make_account, metric, by
):
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    run_job_units(session, jid)
    expected = _numpy_compare(_records(session, jid), jid, metric, by.split(","))
    rows, offset = [], 0
    while True:  # pages of 5
        r = client.get(
            f"{API}/compare",
            params={"jobs": jid, "metric": metric, "by": by, "limit": 5, "offset": offset},
            headers=acc.headers,
        )
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["total"] == len(expected) and body["limit"] == 5
        rows += body["rows"]
        offset += 5
        if offset >= body["total"]:
            break
    keys = [(x["job_id"], *(x[b] for b in by.split(","))) for x in rows]
    assert len(keys) == len(set(keys)) == len(expected)
    # ordered by the by fields (nulls last), then job id
    assert keys == sorted(keys, key=lambda k: tuple((v is None, v or 0) for v in k[1:]) + (k[0],))
    for k, x in zip(keys, rows):
        mean, std, count = expected[k]
        assert x["count"] == count
        if count:
            assert x["mean"] == pytest.approx(mean, rel=1e-12, abs=1e-15)
            assert x["std"] == pytest.approx(std, rel=1e-9, abs=1e-12)
        else:
            assert x["mean"] is None and x["std"] is None


def test_compare_limit_above_cap_is_422(client, session, make_account):
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    r = client.get(
        f"{API}/compare",
        params={"jobs": jid, "metric": "rmse_A", "limit": 10_001},
        headers=acc.headers,
    )
    assert r.status_code == 422 and r.json()["field"] == "limit", r.text
    # an id out of range is named, and so is a list that is too long
    for jobs, said in (("0,1", "0 is not a job id"), (",".join(["1"] * 51), "at most 50 job")):
        r = client.get(
            f"{API}/compare", params={"jobs": jobs, "metric": "rmse_A"}, headers=acc.headers
        )
        assert r.status_code == 422 and r.json()["field"] == "jobs", r.text
        assert r.json()["detail"].startswith(said), r.text


def test_job_list_has_a_spec_summary_and_the_job_the_spec(client, session, make_account):
    acc = make_account()
    big = {**SMALL_SPEC, "N": {"start": 10, "stop": 5000, "step": 1}, "reps": 1}
    jid = client.post(f"{API}/jobs", json=big, headers=acc.headers).json()["id"]
    listed = client.get(f"{API}/jobs", headers=acc.headers)
    (item,) = listed.json()["items"]
    assert "spec" not in item and len(listed.content) < 2000
    full = client.get(f"{API}/jobs/{jid}", headers=acc.headers).json()
    spec = full["spec"]
    assert item["spec_summary"] == {
        "systems": spec["systems"],
        "grid": {"sigma_w": 2, "N": len(spec["N"]), "gamma": 2, "reps": 1},
        "N_range": [min(spec["N"]), max(spec["N"])],
        "estimators": ["ols", "svr"],
        "stages": spec["stages"],
        "n_cells": full["n_cells"],
    }
    assert full["n_cells"] == parse_spec(big).n_cells


def test_partial_summary_in_the_database_equals_numpy_over_the_rows(client, session, make_account):
    from service.db import jobs, units
    from service.db.aggregates import summarize_in_db
    from svrobs_core.records import GROUP_FIELDS, SUMMARY_FIELDS, summarize_columns
    from tests.service.svc_fakes import fake_records

    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    for uid in jobs.unit_ids_of_job(session, jid, pending_only=False)[:3]:
        spec, payload = units.start_unit(session, uid, "w", 60, max_attempts=0)
        units.complete_unit(session, uid, fake_records(spec, payload))
    session.commit()
    recs = _records(session, jid)
    want = summarize_columns({f: [r[f] for r in recs] for f in GROUP_FIELDS + SUMMARY_FIELDS})
    body = client.get(f"{API}/jobs/{jid}/summary", headers=acc.headers).json()
    assert body["partial"] is True and body["groups"] == summarize_in_db(session, jid)
    got = body["groups"]
    assert [tuple(g[k] for k in GROUP_FIELDS) for g in got] == [
        tuple(g[k] for k in GROUP_FIELDS) for g in want
    ]
    for g, w in zip(got, want):
        assert g["count"] == w["count"]
        for f in SUMMARY_FIELDS:
            a, b = g["stats"][f], w["stats"][f]
            assert a["count"] == b["count"], f
            for k in ("mean", "std"):
                if b[k] is None:
                    assert a[k] is None, f
                else:
                    assert a[k] == pytest.approx(b[k], rel=1e-12, abs=1e-15), (f, k)


def test_tick_stores_the_reports_of_recently_finished_jobs(
    client, session, session_factory, make_account
):
    from datetime import timedelta

    from service.db.clock import db_now
    from service.db.models import Job
    from worker.tick import build_reports

    acc = make_account()
    new, old, running = (
        client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
        for _ in range(3)
    )
    run_job_units(session, new)
    run_job_units(session, old)
    session.get(Job, old).finished_at = db_now(session) - timedelta(days=30)
    session.commit()
    assert build_reports(limit=10, scope=scope_of(session_factory)) == [new]
    session.expire_all()
    stored = session.get(JobReport, new)
    assert stored is not None and stored.n_records == len(_records(session, new))
    assert session.get(JobReport, old) is None and session.get(JobReport, running) is None
    page = client.get(f"{API}/jobs/{new}/report", headers=acc.headers)
    assert page.status_code == 200 and page.text == stored.html
    assert build_reports(limit=10, scope=scope_of(session_factory)) == []
