"""Beat's report builds with the crash record (service.report_crashes), on SQLite and
PostgreSQL: a job whose build ended the last process is set aside when the report
thread starts while the other jobs are built, tried again after its pause, and never
built by beat once it has ended the process CRASH_LIMIT times. The page itself is not
drawn here (a stand-in store records which jobs were built)."""

from __future__ import annotations

from service.report_crashes import CRASH_LIMIT, CrashRecord
from tests.service.svc_helpers import scope_of
from tests.service.test_service_reads import _two_finished_jobs


def _started(tick, monkeypatch, path, bad: int, crashes: int):
    """The record a process left that ended ``crashes`` times inside ``bad``'s build,
    read as the report thread's start reads it; builds only recorded."""
    import svrobs_lab.reports as lab_reports

    left = CrashRecord(path)
    left.crashes = {bad: crashes - 1}
    mark = left.in_flight(bad)
    mark.__enter__()  # the mark of the build the process ended in (never left)
    record = CrashRecord(path)
    monkeypatch.setattr(tick, "_crash_record", record)
    monkeypatch.setattr(tick, "_failed_reports", {})
    crashed = record.recover()
    if crashed is not None:
        tick._failed_reports[crashed] = tick.time.monotonic()
    built: list[int] = []
    monkeypatch.setattr(
        lab_reports, "store_if_missing", lambda r, w, job_id, **kw: built.append(job_id) or True
    )
    return record, built, mark


def test_a_job_whose_build_ended_the_process_is_set_aside_then_retried(
    client, session, session_factory, make_account, monkeypatch, tmp_path
):
    from worker import tick

    good, bad = _two_finished_jobs(client, session, make_account())
    record, built, _mark = _started(tick, monkeypatch, tmp_path / "record.json", bad, 1)
    assert record.crashes == {bad: 1}
    scope = scope_of(session_factory)
    assert tick.build_reports(limit=2, scope=scope) == [good] == built
    tick._failed_reports[bad] -= tick.REPORT_RETRY_SECONDS  # its pause is over
    assert tick.build_reports(limit=2, scope=scope) == [bad, good]  # (none was stored)
    assert record.crashes == {}  # built: its count is cleared


def test_a_job_that_ended_the_process_crash_limit_times_is_given_up(
    client, session, session_factory, make_account, monkeypatch, tmp_path
):
    from worker import tick

    good, bad = _two_finished_jobs(client, session, make_account())
    path = tmp_path / "record.json"
    record, built, _mark = _started(tick, monkeypatch, path, bad, CRASH_LIMIT)
    assert record.given_up() == [bad]
    scope = scope_of(session_factory)
    assert tick.build_reports(limit=2, scope=scope) == [good] == built
    tick._failed_reports.clear()  # past any pause: still not built by beat
    assert bad not in tick.build_reports(limit=2, scope=scope) and bad not in built
