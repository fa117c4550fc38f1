"""Report builds (svrobs_lab.report_builds, svrobs_lab.reports): one build per job
at a time, a bounded number per team (429 with Retry-After beyond), the report of a
running job kept until its progress changes, and no database session open while a
report renders."""

from __future__ import annotations

import threading

import pytest

from svrobs_lab import reports
from svrobs_lab.errors import RateLimited
from svrobs_lab.report_builds import ReportBuilds
from tests.service.svc_fakes import run_job_units
from tests.service.svc_helpers import TINY_SPEC, scope_of

API = "/api/v1"


class Gate:
    """A build that blocks until released, counting its calls."""

    def __init__(self, html: str = "<p>r</p>"):
        self.html = html
        self.calls = 0
        self.started = threading.Event()
        self.release = threading.Event()

    def __call__(self) -> str:
        self.calls += 1
        self.started.set()
        assert self.release.wait(10)
        return self.html


def _in_threads(fn, n: int):
    out: list = [None] * n

    def run(i):
        try:
            out[i] = fn()
        except Exception as exc:  # noqa: BLE001 - collected for the assertions
            out[i] = exc

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    return threads, out


def _waiting(builds: ReportBuilds, team: int, n: int) -> bool:
    for _ in range(500):
        if builds._waiting[team] >= n:
            return True
        threading.Event().wait(0.01)
    return False


def test_concurrent_requests_for_one_job_wait_for_one_build():
    builds = ReportBuilds(per_team=2, waiters_per_team=8)
    gate = Gate("<p>one</p>")
    threads, out = _in_threads(lambda: builds.get(1, 10, ("running", 0), gate), 6)
    assert gate.started.wait(5) and _waiting(builds, 10, 5)
    gate.release.set()
    for t in threads:
        t.join(10)
    assert out == ["<p>one</p>"] * 6
    assert gate.calls == 1 and builds.builds == 1
    # kept for that progress: no build; another progress: a new build
    assert builds.get(1, 10, ("running", 0), lambda: pytest.fail("rebuilt")) == "<p>one</p>"
    assert builds.get(1, 10, ("running", 1), lambda: "<p>two</p>") == "<p>two</p>"
    assert builds.builds == 2


def test_a_team_over_its_builds_or_waiters_gets_429_and_other_teams_do_not():
    builds = ReportBuilds(per_team=2, waiters_per_team=1)
    gates = [Gate(f"<p>{i}</p>") for i in range(2)]
    threads = [
        threading.Thread(target=builds.get, args=(job, 10, "v", gates[job])) for job in (0, 1)
    ]
    for t in threads:
        t.start()
    assert all(g.started.wait(5) for g in gates)
    with pytest.raises(RateLimited) as busy:
        builds.get(2, 10, "v", lambda: pytest.fail("a third build of the team ran"))
    assert busy.value.retry_after >= 1 and "REPORT_BUILDS_PER_TEAM" in busy.value.message
    assert builds.get(3, 11, "v", lambda: "<p>other team</p>") == "<p>other team</p>"
    waiter, out = _in_threads(lambda: builds.get(0, 10, "v", gates[0]), 1)
    assert _waiting(builds, 10, 1)
    with pytest.raises(RateLimited):  # a second waiter of the team
        builds.get(1, 10, "v", gates[1])
    for g in gates:
        g.release.set()
    for t in threads + waiter:
        t.join(10)
    assert out == ["<p>0</p>"] and builds.builds == 3
    # the team's builds are done: it may build again
    assert builds.get(2, 10, "v", lambda: "<p>2</p>") == "<p>2</p>"


def test_a_failed_build_fails_its_waiters_and_is_not_kept():
    builds = ReportBuilds(per_team=1, waiters_per_team=4)
    started, release = threading.Event(), threading.Event()

    def boom():
        started.set()
        release.wait(10)
        raise OSError("disk")

    lead, out = _in_threads(lambda: builds.get(1, 1, "v", boom), 1)
    assert started.wait(5)
    waiters, out2 = _in_threads(lambda: builds.get(1, 1, "v", boom), 2)
    assert _waiting(builds, 1, 2)
    release.set()
    for t in lead + waiters:
        t.join(10)
    assert all(isinstance(x, OSError) for x in out + out2)
    assert builds.get(1, 1, "v", lambda: "<p>ok</p>") == "<p>ok</p>"


@pytest.fixture
def counted_render(monkeypatch):
    """A report renderer (a stand-in page) that records, at each call, whether any
    session made by the app's factory was in a transaction while it ran."""
    calls: list[bool] = []

    def render(spec, cols, provenance, **kw):
        calls.append(any(s.in_transaction() for s in OPEN))
        return f"<html><body>{provenance['status']}: {len(cols)} records</body></html>"

    monkeypatch.setattr(reports, "job_report_html", render)
    return calls


OPEN: list = []


@pytest.fixture
def tracked(build_client, session_factory):
    client, _ = build_client()

    def factory(write: bool = True):
        s = session_factory(write)
        OPEN.append(s)
        return s

    client.app.state.session_factory = factory
    yield client
    OPEN.clear()


def test_running_job_report_is_kept_until_its_progress_changes(
    tracked, session, make_account, counted_render
):
    acc = make_account()
    jid = tracked.post(f"{API}/jobs", json=TINY_SPEC, headers=acc.headers).json()["id"]
    first = tracked.get(f"{API}/jobs/{jid}/report", headers=acc.headers)
    assert first.status_code == 200, first.text
    assert tracked.get(f"{API}/jobs/{jid}/report", headers=acc.headers).text == first.text
    assert len(counted_render) == 1
    from service.db.models import Job

    job = session.get(Job, jid)
    job.status, job.cells_done = "running", 1
    session.commit()
    again = tracked.get(f"{API}/jobs/{jid}/report", headers=acc.headers)
    assert again.status_code == 200 and "running" in again.text
    assert len(counted_render) == 2
    # no session of the app was in a transaction while the report rendered
    assert counted_render == [False, False]
    # another team's request builds nothing and finds nothing
    other = make_account()
    assert tracked.get(f"{API}/jobs/{jid}/report", headers=other.headers).status_code == 404
    assert len(counted_render) == 2


def test_report_busy_is_429_with_retry_after(build_client, make_account, monkeypatch):
    client, _ = build_client(REPORT_BUILDS_PER_TEAM=1)
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=TINY_SPEC, headers=acc.headers).json()["id"]

    def busy(*_a, **_k):
        raise RateLimited("this team already builds 1 reports", retry_after=7)

    monkeypatch.setattr(client.app.state.report_builds, "get", busy)
    r = client.get(f"{API}/jobs/{jid}/report", headers=acc.headers)
    assert r.status_code == 429 and r.headers["retry-after"] == "7"
    assert client.app.state.report_builds.per_team == 1


def test_the_columns_are_freed_before_the_memory_is_handed_back(
    tracked, session, session_factory, make_account, monkeypatch
):
    """The build's columns (most of its memory) are garbage when ``_release_memory``
    trims the heap, in both the request's build and the tick's."""
    import weakref

    from sqlalchemy import delete

    from service.db.models import JobReport

    loaded, alive_at_release = [], []
    real_load = reports.load_columns

    def load(*a, **k):
        cols = real_load(*a, **k)
        loaded.append(weakref.ref(cols))
        return cols

    monkeypatch.setattr(reports, "load_columns", load)
    monkeypatch.setattr(
        reports, "_release_memory", lambda: alive_at_release.append(loaded[-1]() is not None)
    )
    acc = make_account()
    jid = tracked.post(f"{API}/jobs", json=TINY_SPEC, headers=acc.headers).json()["id"]
    run_job_units(session, jid)
    session.commit()
    assert tracked.get(f"{API}/jobs/{jid}/report", headers=acc.headers).status_code == 200
    session.execute(delete(JobReport).where(JobReport.job_id == jid))
    session.commit()
    scope = scope_of(session_factory)
    with scope(write=False) as r, scope(write=True) as w:
        assert reports.store_if_missing(r, w, jid)  # the tick's build
    assert len(loaded) == 2 and alive_at_release == [False, False]


def test_a_deleted_jobs_kept_report_is_not_served_for_the_job_that_takes_its_id(
    client, make_account
):
    """The report kept for a deleted job (same status, units and cells as the next
    one) is not served for a job made after it, whichever team made it, even where a
    database would hand its id out again (ids are not: service.db.models.NEVER_REUSED)."""
    a, b = make_account(), make_account()
    jid = client.post(f"{API}/jobs", json={**TINY_SPEC, "name": "a-secret"}, headers=a.headers)
    jid = jid.json()["id"]
    assert "a-secret" in client.get(f"{API}/jobs/{jid}/report", headers=a.headers).text
    assert client.post(f"{API}/jobs/{jid}/cancel", headers=a.headers).status_code == 200
    assert client.delete(f"{API}/jobs/{jid}", headers=a.headers).status_code == 204
    new = client.post(f"{API}/jobs", json={**TINY_SPEC, "name": "b-own"}, headers=b.headers)
    page = client.get(f"{API}/jobs/{new.json()['id']}/report", headers=b.headers)
    assert page.status_code == 200, page.text
    assert "b-own" in page.text and "a-secret" not in page.text
