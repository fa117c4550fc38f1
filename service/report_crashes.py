"""Report builds that ended beat's process (docs/deploy.md#beat-and-report-builds).

Beat's report thread marks the job whose build is in flight in a small JSON file of
its state folder (``SVROBS_VAR_DIR``) before the build and clears the mark after it,
whatever the build's outcome. A mark found when the thread starts is a build that
ended the process (the kernel's OOM killer, a crash in native code): that job's
count goes up, it is set aside like any failed build, and once its builds have ended
the process CRASH_LIMIT times beat never builds it again (its report is then built
at its first request, in the API). So one job whose report cannot be built cannot
keep beat, and with it the schedules, in a restart loop. A stop by the operator is
not a crash: beat clears the mark of a build it abandons at exit, and ``svrobs
serve`` clears it after stopping its processes (also when a second Ctrl-C killed
them).
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

log = logging.getLogger(__name__)

FILE_NAME = "report-build-in-flight.json"
CRASH_LIMIT = 2
UNREADABLE = (ValueError, TypeError, AttributeError, OSError)


class CrashRecord:
    """The in-flight mark and the crash counts, kept in ``path``."""

    def __init__(self, path: Path):
        self.path = path
        self.crashes: dict[int, int] = {}

    def _write(self, in_flight: int | None) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(self.path.name + ".tmp")
        body = {"in_flight": in_flight, "crashes": {str(j): c for j, c in self.crashes.items()}}
        tmp.write_text(json.dumps(body))
        os.replace(tmp, self.path)  # a reader sees the old file or the new one

    def _read(self) -> int | None:
        """Load the counts from the file -> the job marked in flight (None: none).
        FileNotFoundError; ValueError (and the like) when it is not readable."""
        body = json.loads(self.path.read_text())
        self.crashes = {int(j): int(c) for j, c in body.get("crashes", {}).items()}
        crashed = body.get("in_flight")
        return None if crashed is None else int(crashed)

    def recover(self) -> int | None:
        """Read the file (at the thread's start): the job whose build was in flight when
        the last process ended, its count raised and the mark cleared; None if none."""
        try:
            crashed = self._read()
        except FileNotFoundError:
            return None
        except UNREADABLE:
            log.warning("tick: %s is not readable; starting without it", self.path)
            self.crashes, crashed = {}, None
        if crashed is not None:
            self.crashes[crashed] = self.crashes.get(crashed, 0) + 1
            log.error(
                "tick: the report build of job %s ended the process (%d time(s)); %s",
                crashed,
                self.crashes[crashed],
                "beat will not build it again; its first request will"
                if self.crashes[crashed] >= CRASH_LIMIT
                else "set aside for now",
            )
        self._write(None)
        return crashed

    def given_up(self) -> list[int]:
        """The jobs beat no longer builds."""
        return [j for j, c in self.crashes.items() if c >= CRASH_LIMIT]

    @contextmanager
    def in_flight(self, job_id: int) -> Iterator[None]:
        """Mark ``job_id`` in flight while the block runs; a build that returns clears
        the job's count, one that raises keeps it."""
        self._write(job_id)
        try:
            yield
            self.crashes.pop(job_id, None)
        finally:
            self._write(None)

    def clear(self) -> None:
        """Clear the mark, keeping the counts (a build abandoned at a stop did not
        crash)."""
        try:
            self._read()
        except FileNotFoundError:
            return
        except UNREADABLE:
            pass  # recover() says so at the next start
        self._write(None)
