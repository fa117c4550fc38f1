"""Beat's report builds with the crash record (service.report_crashes), on SQLite and
PostgreSQL: a job whose build ended the last process is set aside when the report
thread starts while the other jobs are built, tried again after its pause, and never
built by beat once it has ended the process CRASH_LIMIT times."""

from __future__ import annotations

from service.report_crashes import CRASH_LIMIT, CrashRecord
from tests.reliability.test_report_crashes import _die_building
from tests.service.svc_helpers import scope_of
from tests.service.test_service_reads import _two_finished_jobs


def _started(tick, monkeypatch, path):
    """What the report thread's start does with the record, without the thread."""
    record = CrashRecord(path)
    monkeypatch.setattr(tick, "_crash_record", record)
    monkeypatch.setattr(tick, "_failed_reports", {})
    crashed = record.recover()
    if crashed is not None:
        tick._failed_reports[crashed] = tick.time.monotonic()
    return record


def test_a_job_whose_build_ended_the_process_is_set_aside_then_retried(
    client, session, session_factory, make_account, monkeypatch, tmp_path
):
    from worker import tick

    good, bad = _two_finished_jobs(client, session, make_account())
    path = tmp_path / "record.json"
    _die_building(path, bad)  # a process that ended inside the build
    record = _started(tick, monkeypatch, path)
    assert record.crashes == {bad: 1}
    scope = scope_of(session_factory)
    assert tick.build_reports(limit=2, scope=scope) == [good]
    tick._failed_reports[bad] -= tick.REPORT_RETRY_SECONDS  # its pause is over
    assert tick.build_reports(limit=2, scope=scope) == [bad]
    assert record.crashes == {}  # built: its count is cleared


def test_a_job_that_ended_the_process_crash_limit_times_is_given_up(
    client, session, session_factory, make_account, monkeypatch, tmp_path
):
    from worker import tick

    acc = make_account()
    good, bad = _two_finished_jobs(client, session, acc)
    path = tmp_path / "record.json"
    for _ in range(CRASH_LIMIT):
        _die_building(path, bad)
    record = _started(tick, monkeypatch, path)
    assert record.given_up() == [bad]
    scope = scope_of(session_factory)
    assert tick.build_reports(limit=2, scope=scope) == [good]
    tick._failed_reports.clear()  # past any pause: still not built by beat
    assert tick.build_reports(limit=2, scope=scope) == []
    # its first request builds it, in the API
    r = client.get(f"/api/v1/jobs/{bad}/report", headers=acc.headers)
    assert r.status_code == 200 and "<html" in r.text.lower()
