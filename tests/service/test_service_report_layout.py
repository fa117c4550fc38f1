"""Stored reports and the page layout (``job_reports.layout``,
``svrobs_lab.report_html.REPORT_LAYOUT``): a report stored with another layout is
built again from the job's rows, at its next request and by beat's report thread,
except a pruned job's, which is the only copy and is served as stored. The pages
are a stand-in renderer's (what is tested is which page is served and stored)."""

from __future__ import annotations

import pytest
import sqlalchemy as sa
from sqlalchemy import update

from service.db.migrate import downgrade, upgrade
from service.db.models import JobReport
from service.db.retention import prune_job
from service.db.session import create_db_engine
from svrobs_lab import reports
from svrobs_lab.report_html import REPORT_LAYOUT
from tests.service.svc_fakes import run_job_units
from tests.service.svc_helpers import TINY_SPEC, scope_of
from worker.tick import build_reports

API = "/api/v1"
MARKER = "<p>a page of an old layout</p>"


@pytest.fixture
def renders(monkeypatch):
    """A stand-in renderer (and no heap trim after a build); the list holds the
    number of records of each page built."""
    built: list[int] = []

    def render(spec, cols, provenance, **kw):
        built.append(len(cols))
        return f"<html><body>{provenance['job_id']}: {len(cols)} records</body></html>"

    monkeypatch.setattr(reports, "job_report_html", render)
    monkeypatch.setattr(reports, "_release_memory", lambda: None)  # a full gc: 0.2 s a build
    return built


def _finished_job(client, session, acc) -> int:
    jid = client.post(f"{API}/jobs", json=TINY_SPEC, headers=acc.headers).json()["id"]
    run_job_units(session, jid)
    session.commit()
    return jid


def _stored(session, jid) -> JobReport:
    session.expire_all()
    row = session.get(JobReport, jid)
    assert row is not None
    return row


def _make_old(session, jid) -> None:
    """The stored report as an earlier layout stored it (its page a marker)."""
    session.execute(
        update(JobReport)
        .where(JobReport.job_id == jid)
        .values(layout=REPORT_LAYOUT - 1, html=MARKER)
    )
    session.commit()


def test_an_old_layout_report_is_built_again_at_its_next_request(
    client, session, make_account, renders
):
    acc = make_account()
    jid = _finished_job(client, session, acc)
    first = client.get(f"{API}/jobs/{jid}/report", headers=acc.headers)
    assert first.status_code == 200 and _stored(session, jid).layout == REPORT_LAYOUT
    _make_old(session, jid)
    again = client.get(f"{API}/jobs/{jid}/report", headers=acc.headers)
    assert again.status_code == 200 and MARKER not in again.text and again.text == first.text
    row = _stored(session, jid)
    assert row.layout == REPORT_LAYOUT and row.html == first.text and len(renders) == 2
    # stored with the current layout: served as stored
    assert client.get(f"{API}/jobs/{jid}/report", headers=acc.headers).text == first.text
    assert len(renders) == 2


def test_beat_builds_an_old_layout_report_again(
    client, session, session_factory, make_account, renders
):
    acc = make_account()
    jid = _finished_job(client, session, acc)
    scope = scope_of(session_factory)
    assert build_reports(limit=10, scope=scope) == [jid]
    page = _stored(session, jid).html
    _make_old(session, jid)
    assert build_reports(limit=10, scope=scope) == [jid]
    row = _stored(session, jid)
    assert row.layout == REPORT_LAYOUT and row.html == page and MARKER not in page
    assert build_reports(limit=10, scope=scope) == [] and len(renders) == 2


def test_a_pruned_jobs_old_layout_report_is_served_as_stored(
    client, session, session_factory, make_account, renders, monkeypatch
):
    acc = make_account()
    jid, racing = (_finished_job(client, session, acc) for _ in range(2))
    for j in (jid, racing):
        assert client.get(f"{API}/jobs/{j}/report", headers=acc.headers).status_code == 200
        _make_old(session, j)
    prune_job(session, jid)
    session.commit()
    built = len(renders)
    page = client.get(f"{API}/jobs/{jid}/report", headers=acc.headers)
    assert page.status_code == 200 and page.text == MARKER
    scope = scope_of(session_factory)
    assert build_reports(limit=10, scope=scope) == [racing]  # not the pruned one
    assert _stored(session, jid).html == MARKER and len(renders) == built + 1

    # pruned while its report was built again from the rows: the stored page is kept
    _make_old(session, racing)

    def render_while_pruned(spec, cols, provenance, **kw):
        prune_job(session, racing)
        session.commit()
        return "<html>the rows read before the pruning</html>"

    monkeypatch.setattr(reports, "job_report_html", render_while_pruned)
    page = client.get(f"{API}/jobs/{racing}/report", headers=acc.headers)
    assert page.status_code == 200 and page.text == MARKER
    assert _stored(session, racing).html == MARKER


def test_0014_gives_the_stored_reports_layout_0_and_goes_back(tmp_path):
    url = f"sqlite:///{tmp_path / 'm.db'}"
    upgrade(url, "0013")
    engine = create_db_engine(url)
    with engine.begin() as c:
        c.execute(sa.text("INSERT INTO teams (id, name, created_at) VALUES (1, 't', '2026-01-01')"))
        c.execute(
            sa.text(
                "INSERT INTO jobs (id, team_id, tags, spec, status, progress_done, "
                "progress_total, n_cells, cells_done, provenance, timings, created_at) "
                "VALUES (1, 1, '[]', '{}', 'succeeded', 1, 1, 1, 1, '{}', '{}', '2026-01-01')"
            )
        )
        c.execute(
            sa.text(
                "INSERT INTO job_reports (job_id, html, n_records, built_at) "
                "VALUES (1, 'page', 1, '2026-01-01')"
            )
        )
    upgrade(url, "0014")
    with engine.connect() as c:
        assert c.execute(sa.text("SELECT html, layout FROM job_reports")).all() == [("page", 0)]
    downgrade(url, "0013")
    with engine.connect() as c:
        assert c.execute(sa.text("SELECT job_id, html FROM job_reports")).all() == [(1, "page")]
        assert "layout" not in {col["name"] for col in sa.inspect(c).get_columns("job_reports")}
    engine.dispose()
