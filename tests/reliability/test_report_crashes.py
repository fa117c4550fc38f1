"""Report builds that end beat's process (service.report_crashes): the in-flight mark
survives the process's death (a real os._exit inside the build), the job is counted
when the next process starts, and after CRASH_LIMIT such deaths beat gives it up; a
build that returns clears its count; an unreadable file is a warning, not a stop."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from service.report_crashes import CRASH_LIMIT, CrashRecord

ROOT = Path(__file__).resolve().parents[2]

DIES = """
import os, sys
from pathlib import Path
from service.report_crashes import CrashRecord

record = CrashRecord(Path(sys.argv[1]))
record.recover()
with record.in_flight(int(sys.argv[2])):
    os._exit(9)  # the process ends inside the build (as the OOM killer would end it)
"""


def _die_building(path: Path, job_id: int) -> None:
    p = subprocess.run([sys.executable, "-c", DIES, str(path), str(job_id)], cwd=ROOT, timeout=60)
    assert p.returncode == 9


def test_a_build_that_ends_the_process_is_counted_and_given_up(tmp_path):
    path = tmp_path / "state" / "record.json"
    _die_building(path, 7)
    record = CrashRecord(path)
    assert record.recover() == 7 and record.crashes == {7: 1} and record.given_up() == []
    assert CrashRecord(path).recover() is None  # the mark was cleared: counted once
    for _ in range(CRASH_LIMIT - 1):
        _die_building(path, 7)
    record = CrashRecord(path)
    assert record.recover() == 7 and record.given_up() == [7]
    # another job's death is its own; a build of it that returns clears its count
    _die_building(path, 8)
    record = CrashRecord(path)
    assert record.recover() == 8 and record.crashes == {7: CRASH_LIMIT, 8: 1}
    with record.in_flight(8):
        pass
    assert record.crashes == {7: CRASH_LIMIT}
    assert CrashRecord(path).recover() is None and record.given_up() == [7]


def test_a_build_that_raises_keeps_its_count_and_clears_the_mark(tmp_path):
    path = tmp_path / "record.json"
    _die_building(path, 3)
    record = CrashRecord(path)
    record.recover()
    try:
        with record.in_flight(3):
            raise ValueError("a build that fails")
    except ValueError:
        pass
    fresh = CrashRecord(path)
    assert fresh.recover() is None and fresh.crashes == {3: 1}


def test_an_unreadable_record_is_a_warning(tmp_path, caplog):
    path = tmp_path / "record.json"
    path.write_text("{not json")
    with caplog.at_level("WARNING", logger="service.report_crashes"):
        assert CrashRecord(path).recover() is None
    assert "not readable" in caplog.text
    assert CrashRecord(path).recover() is None  # rewritten readable


def test_clear_keeps_the_counts(tmp_path):
    path = tmp_path / "record.json"
    _die_building(path, 4)  # counted at the next read
    _die_building(path, 5)  # its mark: cleared by a stop, not counted
    CrashRecord(path).clear()
    record = CrashRecord(path)
    assert record.recover() is None and record.crashes == {4: 1}
    CrashRecord(tmp_path / "none.json").clear()  # no file: nothing to clear, none made
    assert not (tmp_path / "none.json").exists()
