"""REST: results filters, pagination, CSV/JSONL streams, summary, compare, presets."""

from __future__ import annotations

import csv
import io
import json

import pytest
from sqlalchemy import select

from service.db.models import WorkUnit
from svrobs_core.records import MATRIX_FIELDS, NUMERIC_FIELDS, RECORD_FIELDS, json_value
from tests.service.svc_fakes import fake_records, run_job_units
from tests.service.svc_helpers import SMALL_SPEC

API = "/api/v1"


@pytest.fixture
def done_job(client, session, make_account):
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    run_job_units(session, jid)
    spec = client.get(f"{API}/jobs/{jid}", headers=acc.headers).json()["spec"]
    units = session.scalars(select(WorkUnit).where(WorkUnit.job_id == jid)).all()
    written = [r for u in units for r in fake_records(spec, u.payload)]
    return acc, jid, [{k: json_value(v) for k, v in r.items()} for r in written]


def _key(r):
    return (
        r["system"],
        r["sigma_w"],
        r["N"],
        r["estimator"],
        -1 if r["gamma"] is None else r["gamma"],
        r["rep"],
    )


def test_results_page_and_filters(client, done_job):
    acc, jid, stored = done_job
    r = client.get(f"{API}/jobs/{jid}/results", headers=acc.headers).json()
    assert r["total"] == 72 and r["limit"] == 100 and len(r["items"]) == 72
    item = r["items"][0]
    assert list(item) == list(RECORD_FIELDS)
    assert isinstance(item["A_hat"], list) and isinstance(item["A_hat"][0], list)
    assert item["rmse_B"] is None  # NaN -> null
    assert [_key(x) for x in r["items"]] == sorted(_key(x) for x in stored)
    by_key = {_key(x): x for x in stored}  # the page equals the records written
    assert all(x == by_key[_key(x)] for x in r["items"])

    def get(**params):
        return client.get(f"{API}/jobs/{jid}/results", params=params, headers=acc.headers)

    f = get(system="paper-unstable", N=40, estimator="svr", gamma=0.1).json()
    assert f["total"] == 2 * 3  # sigma_w x rep
    assert all(
        x["system"] == "paper-unstable" and x["N"] == 40 and x["gamma"] == 0.1 for x in f["items"]
    )
    ols = get(gamma="null").json()
    assert ols["total"] == 24 and {x["estimator"] for x in ols["items"]} == {"ols"}
    two = get(N=[20, 40], rep=[0, 2], sigma_w=0.5).json()
    assert two["total"] == 2 * 2 * 2 * 3
    page1 = get(limit=10).json()
    page2 = get(limit=10, offset=10).json()
    assert len(page1["items"]) == 10 and page1["total"] == 72
    assert page1["items"][-1] != page2["items"][0]
    assert [_key(x) for x in page1["items"] + page2["items"]] == sorted(_key(x) for x in stored)[
        :20
    ]
    assert get(gamma="abc").json()["field"] == "gamma"
    assert get(sigma_w="nan").status_code == 422
    assert get(limit=0).status_code == 422
    assert get(format="xml").json()["field"] == "format"


def _parse_csv_value(field, text):
    if text == "":
        return None
    if field in MATRIX_FIELDS or field == "seed_key":
        return json.loads(text)
    if text in ("true", "false"):
        return text == "true"
    if field in NUMERIC_FIELDS:
        return int(text) if field in ("N", "N0", "rep") else float(text)
    return text


def test_csv_and_jsonl_round_trip(client, done_job):
    acc, jid, stored = done_job
    by_key = {_key(r): r for r in stored}
    r = client.get(f"{API}/jobs/{jid}/results", params={"format": "csv"}, headers=acc.headers)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    rows = list(csv.reader(io.StringIO(r.text)))
    assert rows[0] == list(RECORD_FIELDS)
    parsed = [{f: _parse_csv_value(f, v) for f, v in zip(rows[0], row)} for row in rows[1:]]
    assert len(parsed) == 72
    for rec in parsed:
        assert rec == by_key[_key(rec)]
    r = client.get(
        f"{API}/jobs/{jid}/results", params={"format": "jsonl", "N": 20}, headers=acc.headers
    )
    assert r.headers["content-type"].startswith("application/x-ndjson")
    lines = [json.loads(x) for x in r.text.splitlines()]
    assert len(lines) == 36 and all(x == by_key[_key(x)] for x in lines)
    assert "NaN" not in r.text


def test_summary(client, done_job):
    acc, jid, stored = done_job
    s = client.get(f"{API}/jobs/{jid}/summary", headers=acc.headers).json()
    assert s["partial"] is False and len(s["groups"]) == 24
    g = next(
        x
        for x in s["groups"]
        if x["system"] == "paper-stable"
        and x["sigma_w"] == 0.5
        and x["N"] == 20
        and x["estimator"] == "ols"
    )
    vals = [
        r["rmse_A"]
        for r in stored
        if r["system"] == "paper-stable"
        and r["sigma_w"] == 0.5
        and r["N"] == 20
        and r["estimator"] == "ols"
    ]
    assert g["count"] == 3 and g["gamma"] is None
    assert g["stats"]["rmse_A"]["mean"] == pytest.approx(sum(vals) / 3)
    assert g["stats"]["rmse_B"] == {"mean": None, "std": None, "count": 0}


def test_summary_of_running_job_is_partial(client, session, make_account):
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    s = client.get(f"{API}/jobs/{jid}/summary", headers=acc.headers).json()
    page = {"total": 0, "limit": 10_000, "offset": 0}
    assert s == {"job_id": jid, "partial": True, "groups": [], **page}


def _pages(client, acc, jid, size: int) -> list[dict]:
    """Every group of the job's summary, read in pages of ``size``."""
    out, offset = [], 0
    while True:
        params = {"limit": size, "offset": offset}
        r = client.get(f"{API}/jobs/{jid}/summary", params=params, headers=acc.headers)
        body = r.json()
        assert body["limit"] == size and body["offset"] == offset
        out += body["groups"]
        offset += size
        if offset >= body["total"]:
            return out


def test_summary_pages_stored_and_partial(client, session, make_account):
    """The summary's pages, in grid order, join into the whole summary, for a running
    job (aggregated in the database) and once it succeeded (stored)."""
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    run_job_units(session, jid, count=1)
    whole = client.get(f"{API}/jobs/{jid}/summary", headers=acc.headers).json()
    assert whole["partial"] is True and whole["total"] == len(whole["groups"]) > 5
    assert _pages(client, acc, jid, 5) == whole["groups"]
    run_job_units(session, jid)
    whole = client.get(f"{API}/jobs/{jid}/summary", headers=acc.headers).json()
    assert whole["partial"] is False and whole["total"] == len(whole["groups"]) == 24
    assert _pages(client, acc, jid, 7) == whole["groups"]


def test_compare(client, session, done_job):
    acc, jid, stored = done_job
    jid2 = client.post(f"{API}/jobs", json={**SMALL_SPEC, "N": [20]}, headers=acc.headers).json()[
        "id"
    ]
    run_job_units(session, jid2)
    r = client.get(
        f"{API}/compare",
        params={"jobs": f"{jid},{jid2}", "metric": "rmse_A", "by": "N,estimator"},
        headers=acc.headers,
    )
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["metric"] == "rmse_A" and body["by"] == ["N", "estimator"]
    rows = {(x["job_id"], x["N"], x["estimator"]): x for x in body["rows"]}
    assert set(rows) == {
        (j, n, e)
        for j in (jid, jid2)
        for n in ((20, 40) if j == jid else (20,))
        for e in ("ols", "svr")
    }
    vals = [x["rmse_A"] for x in stored if x["N"] == 40 and x["estimator"] == "svr"]
    assert rows[(jid, 40, "svr")]["count"] == len(vals) == 24
    assert rows[(jid, 40, "svr")]["mean"] == pytest.approx(sum(vals) / len(vals))
    # identical cells in both jobs give the same numbers
    assert rows[(jid, 20, "ols")]["mean"] == pytest.approx(rows[(jid2, 20, "ols")]["mean"])
    b = client.get(
        f"{API}/compare",
        params={"jobs": jid, "metric": "thm1_holds_A", "by": "N"},
        headers=acc.headers,
    ).json()
    assert all(0 <= x["mean"] <= 1 for x in b["rows"])

    def bad(**params):
        r = client.get(f"{API}/compare", params=params, headers=acc.headers)
        assert r.status_code == 422, r.text
        return r.json()["field"]

    assert bad(jobs=jid, metric="notes") == "metric"
    assert bad(jobs=jid, metric="A_hat") == "metric"
    assert bad(jobs=jid, metric="rmse_A", by="N,color") == "by"
    assert bad(jobs="1,x", metric="rmse_A") == "jobs"
    assert bad(metric="rmse_A") == "jobs"


def test_presets(client, make_account):
    acc = make_account()
    r = client.get(f"{API}/presets", headers=acc.headers).json()
    names = [p["name"] for p in r]
    assert "paper-stable" in names and "paper-unstable" in names
    assert r[0]["A"] and r[0]["B"]


def test_record_json_edge_values():
    """The page/line encoder of stored rows: float64 bytes back to the exact floats
    (repr round trip, -0.0 and subnormals kept), non-finite entries and scalars ->
    null, an absent matrix -> null, a derived seed_key rebuilt from the spec and a
    stored one kept, quotes and non-ASCII intact, field order of the record."""
    import numpy as np

    from service.db.result_codec import ResultCodec
    from svrobs_lab.record_json import encode_lines, encode_page

    name = 'sys "q" \u00e9\u2603'
    system = {"name": name, "A": [[0.5, 0.0], [0.0, 0.5]], "B": [[1.0], [0.0]], "C": [[1.0, 0.0]]}
    codec = ResultCodec.of({"systems": ["paper-stable", system], "sigma_w": [0.1, 2.0]})

    def f64(m):
        return np.asarray(m, dtype="<f8").tobytes()

    def row(x, i):
        A = [[x, -2e-300], [1 / 3, -0.0]]
        L = [[float("nan")], [1e300]]
        stored = {
            "system": name,
            "sigma_w": 2.0,
            "A_hat": f64(A),
            "B_hat": None,
            "L": f64(L),
            "K": f64([[0.1], [x]]),
            "radii_A": f64([x]),  # one float: every entry of the matrix
            "radii_B": f64([[0.25], [-0.0]]),
            "bounds_method": "paper",
            "seed_key": None if i % 2 else "[9, 9, 9, 9]",
            "rmse_A": float("nan"),
            "J_mc": float("-inf"),
            "N": 7,
            "N0": 7,
            "rep": i,
            "certified": True,
            "notes": "a \u2603 note" if i % 3 else None,
        }
        out = tuple(stored.get(f, x * len(f)) for f in RECORD_FIELDS)
        want = dict(zip(RECORD_FIELDS, out))
        want.update(
            A_hat=A,
            B_hat=None,
            L=[[None], [1e300]],
            K=[[0.1], [x]],
            radii_A=[[x, x], [x, x]],
            radii_B=[[0.25], [-0.0]],
            seed_key=[1, 1, 7, i] if i % 2 else [9, 9, 9, 9],
            rmse_A=None,
            J_mc=None,
        )
        return out, want

    import random

    rng = random.Random(5)
    pairs = [row(rng.uniform(-1e6, 1e6) * 10 ** rng.randint(-30, 30), i) for i in range(50)]
    rows, wants = [p[0] for p in pairs], [p[1] for p in pairs]
    page = encode_page(rows, codec, total=90, limit=50, offset=4)
    assert b"NaN" not in page and b"Infinity" not in page
    parsed = json.loads(page)
    assert parsed == {"items": wants, "total": 90, "limit": 50, "offset": 4, "next_offset": None}
    assert all(list(x) == list(RECORD_FIELDS) for x in parsed["items"])
    assert str(parsed["items"][0]["A_hat"][1][1]) == "-0.0"
    assert [json.loads(x) for x in encode_lines(rows, codec).decode().splitlines()] == wants


def test_exports_of_a_worker_stored_job_are_the_core_records(client, session, make_account):
    """Every stage (K stored once per (system, sigma_w)), units stored as a worker stores
    them: the JSON lines are the core's records serialised as before the compact format
    (pydantic_core.to_json of the records, NaN -> null), in the results order, and the
    JSON page holds the same records."""
    from pydantic_core import to_json

    from service.db import jobs, units
    from svrobs_core.parsing import parse_spec
    from svrobs_core.runner import run_unit_result

    acc = make_account()
    spec = {
        **SMALL_SPEC,
        "systems": ["paper-unstable"],
        "sigma_w": [1.0, 0.5],
        "N": [40],
        "reps": 2,
        "stages": ["estimate", "bounds", "gain", "cost", "sls"],
        "mc_reps": 1,
        "mc_runs": 20,
    }
    jid = client.post(f"{API}/jobs", json=spec, headers=acc.headers).json()["id"]
    want = []
    for uid in jobs.unit_ids_of_job(session, jid):
        spec_dict, payload = units.start_unit(session, uid, "w", 60, max_attempts=0)
        result = run_unit_result(parse_spec(spec_dict), payload)
        units.complete_unit(session, uid, result)
        want += [{k: json_value(v) for k, v in r.items()} for r in result.records()]
        session.commit()
    want.sort(key=_key)
    r = client.get(f"{API}/jobs/{jid}/results", params={"format": "jsonl"}, headers=acc.headers)
    assert r.content == b"".join(to_json(x, inf_nan_mode="null") + b"\n" for x in want)
    page = client.get(f"{API}/jobs/{jid}/results", headers=acc.headers).json()
    assert page["items"] == json.loads(json.dumps(want)) and page["items"][0]["K"] is not None


def test_page_total_of_a_succeeded_job_is_the_row_count(client, session, done_job):
    """A succeeded job's page total is counted on the spec's grid: it equals SQL's
    COUNT(*) of the same selection for filters on every coordinate."""
    from sqlalchemy import func

    from service.db.models import Result

    acc, jid, _ = done_job
    t = Result.__table__
    cases = [
        ({}, []),
        ({"system": "paper-unstable"}, [t.c.system == "paper-unstable"]),
        ({"sigma_w": [0.5, 7.0]}, [t.c.sigma_w.in_([0.5, 7.0])]),
        ({"N": [20, 20, 99]}, [t.c.N.in_([20, 99])]),
        ({"estimator": "svr", "gamma": "0.1"}, [t.c.estimator == "svr", t.c.gamma_key == 0.1]),
        ({"gamma": ["null", "0.05"]}, [t.c.gamma_key.in_([-1.0, 0.05])]),
        ({"estimator": "ols", "gamma": "0.05"}, [t.c.estimator == "ols", t.c.gamma_key == 0.05]),
        ({"rep": [0, 2, 5, -1]}, [t.c.rep.in_([0, 2, 5, -1])]),
        ({"system": "nope", "N": 40}, [t.c.system == "nope"]),
    ]
    for params, conds in cases:
        want = session.scalar(select(func.count()).select_from(t).where(t.c.job_id == jid, *conds))
        got = client.get(f"{API}/jobs/{jid}/results", params=params, headers=acc.headers).json()
        assert got["total"] == want, params
    assert want == 0 and got["items"] == []


def test_streams_are_bounded_per_team_and_give_their_slot_back(build_client, session, make_account):
    """A CSV or JSON-lines stream reads through one database connection until its
    client has read the last row (sixteen stalled streams of one team made every other
    team's GET a 503 after 30 s on PostgreSQL): a team streams at most
    SVROBS_STREAMS_PER_TEAM at once, 429 with Retry-After beyond; a JSON page and
    another team's stream are not counted; a stream gives its slot back when it ends,
    and when it is dropped unread."""
    import gc

    from svrobs_lab import results
    from svrobs_lab.auth import Caller
    from svrobs_lab.jobs import team_job
    from svrobs_lab.slots import stream_slots

    client, _ = build_client(STREAMS_PER_TEAM=1)
    slots = client.app.state.stream_slots
    jobs = {}
    for acc in (make_account(), make_account()):
        jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
        jobs[jid] = acc
        run_job_units(session, jid)
    (jid, acc), (theirs, other) = jobs.items()
    url = f"{API}/jobs/{jid}/results"
    release = slots.take(acc.team.id)  # a stream of the team's that its client reads slowly
    for fmt in ("csv", "jsonl"):
        busy = client.get(url, params={"format": fmt}, headers=acc.headers)
        assert busy.status_code == 429 and int(busy.headers["retry-after"]) >= 1, busy.text
        assert "SVROBS_STREAMS_PER_TEAM" in busy.json()["detail"]
    assert client.get(url, headers=acc.headers).status_code == 200  # a page: no stream
    r = client.get(f"{API}/jobs/{theirs}/results?format=csv", headers=other.headers)
    assert r.status_code == 200
    release()
    done = client.get(url, params={"format": "jsonl"}, headers=acc.headers)
    assert done.status_code == 200 and len(done.text.splitlines()) == 72
    assert slots.in_use() == 0
    # dropped before its first chunk: the slot comes back with the generator
    caller = Caller(key_id=0, team_id=acc.team.id, user_id=None, is_admin=False)
    sel = results.select_rows(team_job(session, caller, jid))
    own = stream_slots(per_team=1, at_once=1)
    chunks, _ = results.stream(session, client.app.state.session_factory, sel, "csv", slots=own)
    assert own.in_use(acc.team.id) == 1
    del chunks
    gc.collect()
    assert own.in_use() == 0
