"""Schedules across daylight-saving changes (docs/client.md#daylight-saving-time): the
due times that ticks every few minutes find equal a brute-force enumeration of every
UTC minute whose wall-clock time the cron matches (both copies of a repeated hour for
an hour field of ``*``, the first only otherwise; a skipped wall time when its gap
ends), in zones with one-hour and half-hour changes; on the database, an hourly
schedule makes one job per due time through the repeated hour."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from zoneinfo import ZoneInfo

import pytest
from croniter import croniter
from sqlalchemy import select

from service.config import get_settings
from service.db import schedules
from service.db.models import ScheduleRun
from svrobs_lab import schedules as lab_schedules
from tests.service.test_service_crud import _schedule

MINUTE = timedelta(minutes=1)
CRONS = ("0 * * * *", "*/30 * * * *", "30 2 * * *", "15 1,2,3 * * *", "0 0 * * *")
# (zone, a UTC time a few hours before one of its changes)
CHANGES = [
    ("Europe/Paris", datetime(2026, 10, 24, 21, 0, tzinfo=UTC)),  # back, 01:00Z
    ("Europe/Paris", datetime(2026, 3, 28, 21, 0, tzinfo=UTC)),  # forward, 01:00Z
    ("America/New_York", datetime(2026, 11, 1, 2, 0, tzinfo=UTC)),  # back, 06:00Z
    ("America/New_York", datetime(2026, 3, 8, 3, 0, tzinfo=UTC)),  # forward, 07:00Z
    ("Australia/Lord_Howe", datetime(2026, 4, 4, 10, 0, tzinfo=UTC)),  # back 30 min
    ("Australia/Lord_Howe", datetime(2026, 10, 3, 10, 0, tzinfo=UTC)),  # forward 30 min
    ("UTC", datetime(2026, 10, 24, 21, 0, tzinfo=UTC)),
]
HOURS = 8


def brute_force_due(cron: str, zone: ZoneInfo, start: datetime, end: datetime) -> set:
    """Every due time in [start, end): each UTC minute whose wall time matches (its
    second occurrence only with an hour field of *), and each matching wall time
    that no minute shows (skipped), read with the offset before the change."""
    both = cron.split()[1] == "*"
    due, shown = set(), set()
    u = start - timedelta(hours=3)
    while u < end + timedelta(hours=3):
        local = u.astimezone(zone)
        wall = local.replace(tzinfo=None)
        shown.add(wall)
        if croniter.match(cron, wall) and (both or local.fold == 0):
            due.add(u)
        u += MINUTE
    w = (start - timedelta(hours=3)).astimezone(zone).replace(tzinfo=None)
    while w < (end + timedelta(hours=3)).astimezone(zone).replace(tzinfo=None):
        if w not in shown and croniter.match(cron, w):
            due.add(w.replace(tzinfo=zone, fold=0).astimezone(UTC))
        w += MINUTE
    return {d for d in due if start <= d < end}


@pytest.mark.parametrize("cron", CRONS)
@pytest.mark.parametrize("tz,start", CHANGES)
def test_ticks_find_every_due_time_once(cron, tz, start):
    end = start + timedelta(hours=HOURS)
    found, t = set(), start
    while t < end:
        due = schedules.latest_due(cron, tz, t)
        assert due <= t
        if due >= start:
            found.add(due)
        t += 10 * MINUTE  # the crons' due times are 30 minutes apart or more
    assert sorted(found) == sorted(brute_force_due(cron, ZoneInfo(tz), start, end))


def test_the_repeated_hour_in_paris():
    """Clocks back at 01:00Z on 2026-10-25 (03:00 CEST -> 02:00 CET)."""
    back = datetime(2026, 10, 25, 1, 0, tzinfo=UTC)
    at = lambda cron, minutes: schedules.latest_due(  # noqa: E731
        cron, "Europe/Paris", back + minutes * MINUTE
    )
    assert at("0 * * * *", 20) == back  # 02:20 CET: the second 02:00 was due
    assert at("0 * * * *", -40) == back - 60 * MINUTE  # 02:20 CEST: the first
    assert at("30 2 * * *", 40) == back - 30 * MINUTE  # the daily run stays the first
    assert at("30 2 * * *", 40 + 24 * 60) == back - 30 * MINUTE + timedelta(days=1, hours=1)
    forward = datetime(2026, 3, 29, 1, 0, tzinfo=UTC)  # 02:00 CET -> 03:00 CEST
    assert schedules.latest_due("30 2 * * *", "Europe/Paris", forward + 40 * MINUTE) == (
        forward + 30 * MINUTE  # 02:30 does not exist: due at 03:30 CEST
    )


def test_shortest_interval_across_the_changes():
    for tz, start in CHANGES:
        assert schedules.shortest_interval("*/30 * * * *", tz, start=start) == 1800
        assert schedules.shortest_interval("0 * * * *", tz, start=start) >= 1800


def test_an_hourly_schedule_makes_a_job_per_due_time_through_the_repeated_hour(
    session, make_account
):
    acc = make_account()
    s = _schedule(session, acc, cron="0 * * * *", created_at=datetime(2026, 10, 1, tzinfo=UTC))
    session.commit()
    t = datetime(2026, 10, 24, 22, 0, tzinfo=UTC)
    while t <= datetime(2026, 10, 25, 3, 0, tzinfo=UTC):
        lab_schedules.create_due_jobs(get_settings(), session, t)
        session.commit()
        t += 10 * MINUTE
    runs = session.scalars(select(ScheduleRun).where(ScheduleRun.schedule_id == s.id)).all()
    due = sorted(r.due_at for r in runs)
    assert [d.astimezone(UTC).hour for d in due] == [22, 23, 0, 1, 2, 3]
    assert all(r.job_id is not None for r in runs)
