"""Trust, service side, in process (SQLite, and PostgreSQL when SVROBS_TEST_DATABASE_URL
is set): admission by estimated work, the per-team fair share of units in flight,
schedule limits and skipped runs, strict input, what a system name does to the CSV and
JSON-lines exports, revoke-key.
The real-process side (latencies, cancel, leases, a MemoryError) is
tests/integration/test_trust.py."""

from __future__ import annotations

import csv
import io
import json
from datetime import UTC, datetime, timedelta

import pytest
from sqlalchemy import select, update

from service.config import get_settings
from service.db import accounts, jobs, outbox, units
from service.db.models import ApiKey, Job, Schedule, ScheduleRun, WorkUnit
from svrobs_cli.app import app
from svrobs_core.admission import smallest_unit_bytes
from svrobs_core.parsing import parse_spec
from svrobs_core.workload import estimate_job, estimate_unit
from svrobs_lab import schedules as lab_schedules
from tests.service.svc_fakes import fake_records
from tests.service.svc_helpers import BIG_MEMORY_SPEC as BIG_MEMORY
from tests.service.svc_helpers import HEAVY_SPEC as HEAVY
from tests.service.svc_helpers import ITEM6_SPEC as ITEM6
from tests.service.svc_helpers import SMALL_SPEC, RecordingPublisher
from tests.web.helpers import csrf_of, sign_in

API = "/api/v1"
MANY_UNITS = {**SMALL_SPEC, "systems": ["paper-stable"], "sigma_w": [0.1 * i for i in range(1, 11)]}


@pytest.fixture
def settings_env(monkeypatch):
    """Set SVROBS_* variables for code that reads get_settings() (the front ends)."""

    def setenv(**kw):
        for k, v in kw.items():
            monkeypatch.setenv(f"SVROBS_{k}", str(v))
        get_settings.cache_clear()

    yield setenv
    get_settings.cache_clear()


# --------------------------------------------------------------------------- admission


def test_item6_spec_is_refused(client, make_account):
    """A cell of about 11 h of CPU: over the core's hard cap."""
    acc = make_account()
    r = client.post(f"{API}/jobs", json=ITEM6, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "mc_runs", r.text


def test_heavy_spec_gets_422_naming_the_estimate_and_the_limit(client, make_account):
    """Within every hard cap but ~2.6 h of CPU: refused by the estimate."""
    acc = make_account()
    before = client.get(f"{API}/jobs", headers=acc.headers).json()["total"]
    r = client.post(f"{API}/jobs", json=HEAVY, headers=acc.headers)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert r.json()["field"] in ("horizon", "mc_runs", "reps", "mc_reps")
    assert "CPU seconds" in detail and "3600" in detail and "SVROBS_MAX_JOB_CPU_SECONDS" in detail
    # the estimate quoted is the cost model's (an oracle independent of the message text)
    assert f"{estimate_job(parse_spec(HEAVY)).cpu_seconds:.0f}" in detail
    assert client.get(f"{API}/jobs", headers=acc.headers).json()["total"] == before


def test_memory_cap_refuses_a_unit_that_cannot_be_split(client, make_account):
    acc = make_account()
    r = client.post(f"{API}/jobs", json=BIG_MEMORY, headers=acc.headers)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert "MB" in detail and "2048 MB" in detail and "SVROBS_MAX_UNIT_MEMORY_MB" in detail
    need = smallest_unit_bytes(parse_spec(BIG_MEMORY)) / 2**20
    assert f"{need:.0f} MB" in detail


def test_units_are_planned_under_the_memory_cap(build_client, make_account, session):
    """With a low cap the job is split into more units, each estimated under the cap."""
    spec = {**SMALL_SPEC, "N": [2000, 4000], "reps": 20, "T0": 50}
    parsed = parse_spec(spec)
    plain = jobs.admit(parsed, max_unit_mb=10**6)
    worst = max(estimate_unit(parsed, u).peak_bytes for u in plain)
    cap_mb = int(worst / 2**20 * 0.6)
    client, _ = build_client(MAX_UNIT_MEMORY_MB=cap_mb)
    acc = make_account()
    r = client.post(f"{API}/jobs", json=spec, headers=acc.headers)
    assert r.status_code == 202, r.text
    stored = session.scalars(select(WorkUnit).where(WorkUnit.job_id == r.json()["id"])).all()
    assert len(stored) > len(plain)
    assert all(estimate_unit(parsed, u.payload).peak_bytes <= cap_mb * 2**20 for u in stored)
    assert sum(u.n_cells for u in stored) == parsed.n_cells


def test_run_local_refuses_a_spec_over_the_service_limit(tmp_path, capsys, settings_env):
    """run-local applies the service's SVROBS_MAX_JOB_CPU_SECONDS (here lowered)."""
    settings_env(MAX_JOB_CPU_SECONDS=1)
    spec = {**SMALL_SPEC, "stages": ["estimate", "bounds", "gain", "cost"], "mc_runs": 5000}
    path = tmp_path / "spec.json"
    path.write_text(json.dumps(spec))
    with pytest.raises(SystemExit) as exc:
        app(["run-local", str(path), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert err.startswith("error: invalid spec: ") and "the job needs an estimated" in err
    assert "over the limit of 1 s (SVROBS_MAX_JOB_CPU_SECONDS)" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- fair share


def _team_job(session, acc, spec) -> tuple[int, list[int]]:
    job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=spec)
    session.commit()
    return job.id, jobs.unit_ids_of_job(session, job.id)


def _dispatch(session_factory, pub, **kw) -> int:
    from contextlib import contextmanager

    @contextmanager
    def begin():
        s = session_factory()
        try:
            yield s
            s.commit()
        finally:
            s.close()

    return outbox.dispatch(begin, pub, **{"retry_seconds": 600, **kw})


def test_dispatch_keeps_k_units_per_team_in_flight(session, session_factory, make_account):
    a, b = make_account(), make_account()
    _, b_units = _team_job(session, b, MANY_UNITS)
    pub = RecordingPublisher()
    assert _dispatch(session_factory, pub, team_id=b.team.id, cap=3) == 3
    assert pub.published == b_units[:3]
    assert _dispatch(session_factory, pub, team_id=b.team.id, cap=3) == 0  # full
    _, a_units = _team_job(session, a, MANY_UNITS)
    assert _dispatch(session_factory, pub, team_id=a.team.id, cap=3) == 3  # A is not behind B
    assert pub.published[3:] == a_units[:3]
    # one of B's units finishes: exactly one more of B's is published
    claimed = units.start_unit(session, b_units[0], "w", 60, max_attempts=0)
    units.complete_unit(session, b_units[0], fake_records(*claimed))
    session.commit()
    assert _dispatch(session_factory, pub, team_id=b.team.id, cap=3) == 1
    assert pub.published[-1] == b_units[3]
    # the tick: every team, round-robin, oldest first, within the cap
    for uid in b_units[1:3] + a_units[:3]:
        claimed = units.start_unit(session, uid, "w", 60, max_attempts=0)
        units.complete_unit(session, uid, fake_records(*claimed))
    session.commit()
    pub.calls.clear()
    _dispatch(session_factory, pub, cap=3, republish=True)
    got = pub.published
    assert sorted(got) == sorted(b_units[4:6] + a_units[3:6])
    teams = "".join("a" if u in a_units else "b" for u in got)
    assert teams == "ababa"  # team a (made first) leads


def test_dispatch_leaves_a_pool_process_to_another_team(session, session_factory, make_account):
    """Alone, a team fills the pool (cap 3); while another team has units queued or
    running it gets one process less (shared cap 2), the other team too."""
    a, b = make_account(), make_account()
    _, a_units = _team_job(session, a, MANY_UNITS)
    pub = RecordingPublisher()
    caps = {"cap": 3, "shared_cap": 2}
    assert _dispatch(session_factory, pub, team_id=a.team.id, **caps) == 3
    _, b_units = _team_job(session, b, MANY_UNITS)
    assert _dispatch(session_factory, pub, team_id=b.team.id, **caps) == 2
    assert pub.published == a_units[:3] + b_units[:2]

    def finish(uid):
        claimed = units.start_unit(session, uid, "w", 60, max_attempts=0)
        units.complete_unit(session, uid, fake_records(*claimed))
        session.commit()

    finish(a_units[0])  # A: 2 in flight, B has work: A's next waits
    assert _dispatch(session_factory, pub, team_id=a.team.id, **caps) == 0
    finish(a_units[1])
    assert _dispatch(session_factory, pub, team_id=a.team.id, **caps) == 1
    assert pub.published[-1] == a_units[3]
    jobs.cancel_job(session, session.get(Job, session.get(WorkUnit, b_units[0]).job_id))
    session.commit()  # B has no work left: A fills the pool again
    assert _dispatch(session_factory, pub, team_id=a.team.id, **caps) == 1
    assert pub.published[-1] == a_units[4]


def test_units_the_broker_did_not_take_are_not_counted_in_flight(
    session, session_factory, make_account
):
    acc = make_account()
    _, ids = _team_job(session, acc, MANY_UNITS)
    down = RecordingPublisher()
    down.fail = True
    assert _dispatch(session_factory, down, team_id=acc.team.id, cap=2) == 0
    assert outbox.in_flight(session, [acc.team.id]) == {}
    up = RecordingPublisher()
    assert _dispatch(session_factory, up, team_id=acc.team.id, cap=2) == 2
    assert up.published == ids[:2]


@pytest.mark.parametrize("where", ["api", "page"])
def test_cancel_frees_the_team_slots_for_its_other_jobs(build_client, make_account, session, where):
    """The API's cancel and the job page's Cancel button alike."""
    client, pub = build_client(MAX_UNITS_IN_FLIGHT_PER_TEAM=2)
    acc = make_account()
    first = client.post(f"{API}/jobs", json=MANY_UNITS, headers=acc.headers).json()
    second = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()
    first_units = jobs.unit_ids_of_job(session, first["id"])
    assert pub.published == first_units[:2]
    if where == "api":
        r = client.post(f"{API}/jobs/{first['id']}/cancel", headers=acc.headers)
        assert r.status_code == 200 and r.json()["cells_done"] == 0
    else:
        sign_in(client, acc.key)
        token = csrf_of(client.get(f"/jobs/{first['id']}").text)
        r = client.post(
            f"/jobs/{first['id']}/cancel", data={"csrf_token": token}, follow_redirects=False
        )
        assert r.status_code == 303
    assert pub.published[2:] == jobs.unit_ids_of_job(session, second["id"])[:2]


# --------------------------------------------------------------------------- schedules


def test_schedule_limits(build_client, make_account):
    client, _ = build_client(MAX_SCHEDULES_PER_TEAM=2)
    acc = make_account()

    def post(**kw):
        body = {"name": "s", "cron": "0 2 * * *", "spec_template": SMALL_SPEC, **kw}
        return client.post(f"{API}/schedules", json=body, headers=acc.headers)

    r = post(cron="*/2 * * * *")
    assert r.status_code == 422 and r.json()["field"] == "cron"
    assert "120 s apart" in r.json()["detail"] and "300" in r.json()["detail"]
    assert post(name="   ").json()["field"] == "name"
    assert post(name="ok", enabled="yes").json()["field"] == "enabled"
    first = post(name="  every five  ", cron="*/5 * * * *")
    assert first.status_code == 201 and first.json()["name"] == "every five"
    assert post(name="two").status_code == 201
    r = post(name="three")
    assert r.status_code == 422 and "SVROBS_MAX_SCHEDULES_PER_TEAM" in r.json()["detail"]
    assert "limit is 2" in r.json()["detail"]
    sid = first.json()["id"]
    r = client.patch(f"{API}/schedules/{sid}", json={"cron": "* * * * *"}, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "cron"
    r = client.patch(f"{API}/schedules/{sid}", json={"name": " "}, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "name"


def test_validate_template_maps_only_spec_errors(client, make_account, monkeypatch):
    """A bug in validation (a TypeError) is a 500 logged with its traceback, not a 422
    that blames the user's template."""
    from svrobs_lab import schedules as route

    def broken(spec):
        raise TypeError("a bug")

    monkeypatch.setattr(route, "parse_spec", broken)
    acc = make_account()
    body = {"name": "x", "cron": "0 2 * * *", "spec_template": SMALL_SPEC}
    r = client.post(f"{API}/schedules", json=body, headers=acc.headers)
    assert r.status_code == 500 and r.json() == {"detail": "internal error", "field": None}


def _schedule(session, acc, **kw) -> Schedule:
    s = Schedule(
        team_id=acc.team.id,
        user_id=acc.user.id,
        name=kw.pop("name", "tick"),
        cron=kw.pop("cron", "*/5 * * * *"),
        timezone="UTC",
        spec_template=kw.pop("spec_template", SMALL_SPEC),
        tags=[],
        created_at=datetime(2024, 1, 1, tzinfo=UTC),
        updated_at=datetime(2024, 1, 1, tzinfo=UTC),
    )
    session.add(s)
    session.commit()
    return s


def _runs(session, sched) -> list[ScheduleRun]:
    q = select(ScheduleRun).where(ScheduleRun.schedule_id == sched.id).order_by(ScheduleRun.due_at)
    return list(session.scalars(q))


def test_tick_applies_the_team_cap_and_records_why(session, make_account, settings_env):
    settings_env(MAX_QUEUED_JOBS_PER_TEAM=1)
    acc = make_account()
    jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC)
    sched = _schedule(session, acc)
    made = lab_schedules.create_due_jobs(
        get_settings(), session, datetime(2024, 6, 1, 12, 1, tzinfo=UTC)
    )
    session.commit()
    assert made == []
    (run,) = _runs(session, sched)
    assert run.job_id is None and run.error is None
    assert "limit is 1" in run.skipped_reason and "QUEUED_JOBS_PER_TEAM" in run.skipped_reason
    n = session.scalar(select(Job.id).where(Job.schedule_id == sched.id))
    assert n is None


def test_tick_skips_runs_closer_than_the_minimum_interval(session, make_account, settings_env):
    """A schedule stored before the limit (cron every minute) runs at most every 300 s."""
    settings_env(MIN_SCHEDULE_INTERVAL_SECONDS=300)
    acc = make_account()
    sched = _schedule(session, acc, cron="* * * * *")
    t = datetime(2024, 6, 1, 12, 0, 30, tzinfo=UTC)
    for k in range(7):
        lab_schedules.create_due_jobs(get_settings(), session, t + timedelta(minutes=k))
        session.commit()
    runs = _runs(session, sched)
    assert [r.job_id is not None for r in runs] == [True, False, False, False, False, True, False]
    assert all("minimum is 300 s" in r.skipped_reason for r in runs if r.job_id is None)


def test_tick_refuses_a_template_over_the_work_limit(session, make_account):
    acc = make_account()
    sched = _schedule(session, acc, spec_template=HEAVY)
    lab_schedules.create_due_jobs(get_settings(), session, datetime(2024, 6, 1, 12, 1, tzinfo=UTC))
    session.commit()
    (run,) = _runs(session, sched)
    assert run.job_id is None and "SVROBS_MAX_JOB_CPU_SECONDS" in run.error


# --------------------------------------------------------------------------- strict input


@pytest.mark.parametrize("value", ["٣٠", "+30", "3_0", "30.0", "-30", "", "1,x"])
def test_compare_jobs_accepts_only_ascii_digits(client, make_account, value):
    acc = make_account()
    r = client.get(
        f"{API}/compare", params={"jobs": value, "metric": "rmse_A"}, headers=acc.headers
    )
    assert r.status_code == 422 and r.json()["field"] == "jobs", r.text


@pytest.mark.parametrize(
    ("path", "params", "field"),
    [
        ("/jobs", {"limit": "+5"}, "limit"),
        ("/jobs", {"offset": "1_0"}, "offset"),
        ("/jobs/{id}/results", {"N": "٣٠"}, "N"),
        ("/jobs/{id}/results", {"rep": "3.0"}, "rep"),
        ("/jobs/{id}/results", {"sigma_w": "1_0"}, "sigma_w"),
        ("/jobs/{id}/results", {"gamma": "٠.٥"}, "gamma"),
        ("/jobs/{id}/results", {"limit": "1e3"}, "limit"),
    ],
)
def test_query_numbers_are_strict(client, make_account, path, params, field):
    acc = make_account()
    session = client.app.state.session_factory()
    job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC)
    session.commit()
    r = client.get(f"{API}{path.format(id=job.id)}", params=params, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] in (field, f"{field}[0]"), r.text


@pytest.mark.parametrize(
    ("extra", "field"),
    [({"reps": 3.0}, "reps"), ({"N": [10.0]}, "N[0]"), ({"name": "   "}, "name")],
)
def test_job_bodies_are_strict(client, make_account, extra, field):
    acc = make_account()
    r = client.post(f"{API}/jobs", json={**SMALL_SPEC, **extra}, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == field, r.text


def test_tags_are_stripped_and_blank_ones_rejected(client, make_account):
    acc = make_account()
    r = client.post(f"{API}/jobs", json={**SMALL_SPEC, "tags": ["  "]}, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "tags[0]"
    r = client.post(f"{API}/jobs", json={**SMALL_SPEC, "tags": [" a "]}, headers=acc.headers)
    assert r.status_code == 202 and r.json()["tags"] == ["a"]


# --------------------------------------------------------------------------- exports

# a system name that is a formula once a spreadsheet splits its line on ";" (LibreOffice
# and Excel do, by locale or by choice); a name holds no tab or line separator (the
# spec refuses them), the notes below do
EXPORT_SYSTEM = "sys;=1+1;@SUM(A1)"


def _job_with_texts(session, acc, texts):
    """A stored job on a system named EXPORT_SYSTEM, whose records' notes are ``texts``
    in turn and whose rmse_A is -0.25."""
    A = [[0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.5]]
    system = {"name": EXPORT_SYSTEM, "A": A, "B": [[1.0], [0.0], [0.0]]}
    spec = {**SMALL_SPEC, "systems": [system], "sigma_w": [1.0], "N": [20]}
    job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=spec)
    session.commit()
    (uid,) = jobs.unit_ids_of_job(session, job.id)
    spec_dict, payload = units.start_unit(session, uid, "w", 60, max_attempts=0)
    recs = fake_records(spec_dict, payload)
    for r, t in zip(recs, texts * len(recs)):
        r["notes"] = t
        r["rmse_A"] = -0.25  # a negative number stays a number
    units.complete_unit(session, uid, recs)
    session.commit()
    return job.id, len(recs)


def test_csv_escapes_formulas_and_quotes_every_text_cell(client, make_account, session):
    acc = make_account()
    texts = ['=HYPERLINK("http://x","y")', "+1", "-2", "@SUM(A1)", "\tx", "\rx", "plain"]
    jid, _ = _job_with_texts(session, acc, texts)
    r = client.get(f"{API}/jobs/{jid}/results", params={"format": "csv"}, headers=acc.headers)
    rows = list(csv.DictReader(io.StringIO(r.text, newline="")))
    got = {row["notes"] for row in rows}
    assert got == {"'" + t for t in texts[:-1]} | {"plain"}
    assert {row["rmse_A"] for row in rows} == {"-0.25"} and ",-0.25," in r.text
    assert {row["system"] for row in rows} == {EXPORT_SYSTEM}
    # split on ";" or a tab, the system name (the line's first cell, quoted) stays one
    # cell: every cell starting like a formula is a number
    assert r.text.split("\r\n")[1].startswith(f'"{EXPORT_SYSTEM}",')
    for delimiter in (";", "\t"):
        for row in csv.reader(io.StringIO(r.text, newline=""), delimiter=delimiter):
            for cell in row:
                if cell.startswith(("=", "+", "-", "@")):
                    float(cell)


def test_json_lines_are_lines_to_every_reader(client, make_account, session):
    acc = make_account()
    jid, n = _job_with_texts(session, acc, ["a\u2028b\x85c\u2029d"])
    url = f"{API}/jobs/{jid}/results"
    r = client.get(url, params={"format": "jsonl"}, headers=acc.headers)
    assert r.text.isascii()
    lines = r.text.splitlines()  # as httpx's iter_lines splits them
    assert len(lines) == n and all(json.loads(x)["system"] == EXPORT_SYSTEM for x in lines)
    page = client.get(url, params={"limit": 1}, headers=acc.headers)
    assert page.json()["items"][0]["notes"] == "a\u2028b\x85c\u2029d" and page.text.isascii()


# --------------------------------------------------------------------------- revoke-key


def test_revoke_key_takes_a_prefix_or_an_explicit_id(tmp_path, monkeypatch, capsys):
    url = f"sqlite:///{tmp_path / 'cli.db'}"
    monkeypatch.setenv("SVROBS_DATABASE_URL", url)
    get_settings.cache_clear()
    from service.db.migrate import upgrade
    from service.db.session import dispose_all, session_scope

    try:
        upgrade(url)
        with session_scope(url) as s:
            accounts.create_team(s, "lab")
            accounts.create_user(s, "lab", "a@lab.org")
            first, _ = accounts.create_key(s, "a@lab.org")  # id 1
            second, _ = accounts.create_key(s, "a@lab.org")  # id 2
            digits = f"{first.id:08d}"  # "00000001": a prefix that looks like an id
            s.execute(update(ApiKey).where(ApiKey.id == second.id).values(prefix=digits))
            ids = (first.id, second.id)

        def run(*args):
            try:
                app(list(args))
                return 0
            except SystemExit as e:
                return e.code or 0

        def revoked():
            with session_scope(url, write=False) as s:
                return {k.id for k in s.scalars(select(ApiKey)) if k.revoked_at is not None}

        assert run("admin", "revoke-key", digits) == 0
        assert revoked() == {ids[1]}  # the key with that prefix, not key id 1
        assert run("admin", "revoke-key", "--id", str(ids[0])) == 0
        assert revoked() == set(ids)
        capsys.readouterr()
        assert run("admin", "revoke-key") == 2
        assert run("admin", "revoke-key", "abc", "--id", "1") == 2
        assert "exactly one" in capsys.readouterr().err
        assert run("admin", "revoke-key", "1") == 2  # no key has the prefix "1"
    finally:
        dispose_all()
        get_settings.cache_clear()
