"""svrobs_client against a real server (uvicorn + celery worker as real processes).

The oracles are the API itself, read with plain httpx: the JSONL export, the summary
and compare JSON, the report page and the error bodies; and pandas' own group-by of
the records for the summary and compare statistics.
"""

from __future__ import annotations

import base64
import io
import json
import re
from datetime import datetime, timedelta

import httpx
import numpy as np
import pandas as pd
import pytest

import svrobs_client
from svrobs_client import (
    AuthError,
    Client,
    ConfigError,
    Conflict,
    ConnectionFailed,
    NotFound,
    ValidationError,
)
from svrobs_client.progress import RichBar
from svrobs_core.records import MATRIX_FIELDS, RECORD_FIELDS, SUMMARY_FIELDS
from tests.integration.stack import cell_key, fetch_jsonl, free_port, same
from tests.integration.test_stack import TINY_SPEC

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

# 8 cells: 2 N x (ols + svr at one gamma) x 2 reps, with gains (L, K) for the matrix fields
SPEC = {**TINY_SPEC, "N": [10, 20], "stages": ["estimate", "bounds", "gain"], "seed": 3}
QUICK = {**SPEC, "N": [10], "stages": ["estimate"], "reps": 1}  # 2 cells


@pytest.fixture(scope="module")
def client(stack):
    with Client(stack.base_url, stack.key, poll_interval=0.25) as c:
        yield c


@pytest.fixture(scope="module")
def job(client):
    job = client.submit(SPEC, name="client-test", tags=["client"], timeout=150)
    assert job.status == "succeeded", job
    return job


def _py(value):
    """A DataFrame cell as the plain Python value JSON would give."""
    return value.item() if isinstance(value, np.generic) else value


def _missing(value) -> bool:
    return value is None or (not isinstance(value, (list, np.ndarray)) and pd.isna(value))


def test_client_matrix_fields_are_the_records():
    assert svrobs_client.MATRIX_FIELDS == MATRIX_FIELDS


# --------------------------------------------------------------------------- results


def test_results_frame_equals_jsonl_export(client, job, http):
    """The DataFrame equals GET /results?format=jsonl cell by cell; matrices are float
    arrays equal to the exported nested lists."""
    exported = fetch_jsonl(http, job.id)
    df = client.results(job)
    assert list(df.columns) == list(RECORD_FIELDS)
    assert len(df) == len(exported) == job.n_cells == 8
    problems = []
    for i, rec in enumerate(exported):
        row = df.iloc[i]
        for f in RECORD_FIELDS:
            got, want = row[f], rec[f]
            if f in MATRIX_FIELDS:
                assert want is not None, f  # estimate and gain ran: every matrix is there
                assert isinstance(got, np.ndarray) and got.dtype == np.float64, (f, got)
                np.testing.assert_array_equal(got, np.array(want, dtype=float))
                assert got.shape == (len(want), len(want[0]))
            elif want is None:
                if not _missing(got):
                    problems.append(f"{i}.{f}: {got!r} != None")
            else:
                problems += same(_py(got), want, f"{i}.{f}")
    assert not problems, "\n".join(problems[:20])


def test_results_filters_and_records(client, job, http):
    exported = fetch_jsonl(http, job.id)
    assert client.results_records(job) == exported
    svr20 = [r for r in exported if r["estimator"] == "svr" and r["N"] == 20]
    assert client.results_records(job, estimator="svr", N=20) == svr20
    assert client.results_records(job.id, estimator=["svr"], N=[20], gamma=0.05) == svr20
    ols = [r for r in exported if r["gamma"] is None]
    assert ols and client.results_records(job, gamma=None) == ols
    df = client.results(job, rep=[1], N=(10, 20))
    assert sorted(map(cell_key, client.results_records(job, rep=1))) == sorted(
        cell_key(r) for r in exported if r["rep"] == 1
    )
    assert set(df["rep"]) == {1} and len(df) == 4
    assert client.results_records(job, limit=3, offset=2) == exported[2:5]
    assert len(client.results(job, system="no-such-system")) == 0
    with pytest.raises(TypeError, match="unknown results filter"):
        client.results(job, rmse_X_lt=0.1)


def test_client_field_lists_are_the_records():
    from service.db.result_queries import RANGE_FIELDS
    from svrobs_core.records import NUMERIC_FIELDS

    assert svrobs_client.NUMERIC_FIELDS == NUMERIC_FIELDS
    assert svrobs_client.RANGE_FIELDS == RANGE_FIELDS


def _nulls_last(field: str, desc: bool):
    """A sort key of one field as SQL orders it: nulls last either way."""
    return lambda r: (
        r[field] is None,
        0 if r[field] is None else (-r[field] if desc else r[field]),
    )


def test_results_sort_and_ranges_equal_the_export(client, job, http):
    """sort and range filters equal Python's stable sort / filter of the JSONL export
    (whose order is the grid order, the server's tie-break)."""
    exported = fetch_jsonl(http, job.id)
    by_rmse = sorted(exported, key=_nulls_last("rmse_A", True))
    want = sorted(by_rmse, key=_nulls_last("N", False))  # -> N asc, then rmse_A desc
    assert client.results_records(job, sort="N,-rmse_A") == want
    assert client.results_records(job, sort=["-rmse_A"]) == by_rmse
    assert list(client.results(job, sort="-rmse_A")["rmse_A"]) == [r["rmse_A"] for r in by_rmse]
    values = sorted(r["rmse_A"] for r in exported)
    cut = values[len(values) // 2]
    below = [r for r in exported if r["rmse_A"] < cut]
    assert 0 < len(below) < len(exported)
    assert client.results_records(job, rmse_A_lt=cut) == below
    assert client.results_records(job, rmse_A_gte=cut, N_lte=10) == [
        r for r in exported if r["rmse_A"] >= cut and r["N"] <= 10
    ]
    with_eps = [r for r in exported if r["eps_A"] is not None and r["eps_A"] > 0]
    assert any(r["estimator"] == "svr" for r in with_eps)
    assert client.results_records(job, eps_A_gt=0, estimator="svr", sort="-eps_A") == sorted(
        [r for r in with_eps if r["estimator"] == "svr"], key=_nulls_last("eps_A", True)
    )


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"sort": "-rmse_X"}, ValueError, "sort: 'rmse_X' is not a numeric record field"),
        ({"sort": "a,b,c,d,e,f"}, ValueError, "1 to 5"),
        ({"rmse_X_lt": 1}, TypeError, "unknown results filter 'rmse_X_lt'"),
        ({"certified_gt": 0}, TypeError, "certified is a yes/no field"),
        ({"rmse_A_lt": "small"}, ValueError, "rmse_A_lt must be a number"),
        ({"rmse_A_lt": float("nan")}, ValueError, "rmse_A_lt must be finite"),
        ({"rmse_A_lt": True}, TypeError, "rmse_A_lt must be a number"),
    ],
)
def test_results_params_checked_before_any_request(kwargs, error, match, tmp_path):
    """A typo raises before a request: the client points at a closed port, so reaching
    the network would be a ConnectionFailed; no file is written."""
    out = tmp_path / "r.csv"
    with Client(f"http://127.0.0.1:{free_port()}", "k", timeout=2) as nowhere:
        with pytest.raises(error, match=match):
            nowhere.results_records(1, **kwargs)
        with pytest.raises(error, match=match):
            nowhere.download_results(1, out, **kwargs)
    assert list(tmp_path.iterdir()) == []


def test_server_422_is_the_backstop(client, job):
    """What the client would refuse, the server refuses too, naming the parameter."""
    path = f"/jobs/{job.id}/results"
    for params, field in [
        ({"sort": "-rmse_X"}, "sort"),
        ({"rmse_X_lt": "1"}, "rmse_X_lt"),
        ({"rmse_A_lt": "small"}, "rmse_A_lt"),
    ]:
        with pytest.raises(ValidationError) as err:
            client.request("GET", path, params=params)
        assert (err.value.status, err.value.field) == (422, field)


# --------------------------------------------------------------------------- share links


def test_share_links(client, job, http):
    """A link opens without a key (plain httpx) until revoked, then it is a 404."""
    share = client.share(job, days=2)
    assert share.job_id == job.id and share.live and share.revoked_at is None
    assert share.url.endswith(f"/s/{share.token}") and len(share.token) >= 20
    assert share.expires_at - share.created_at == timedelta(days=2)
    assert httpx.get(share.url, timeout=30).status_code == 200
    default = client.share(job.id)
    assert default.expires_at - default.created_at == timedelta(days=7)
    listed = client.shares(job)
    assert [s.raw for s in listed] == http.get(f"/jobs/{job.id}/shares").json()
    assert {share.id, default.id} <= {s.id for s in listed}
    assert all(s.url is None for s in listed)  # the token is shown once
    client.revoke_share(share)
    assert httpx.get(share.url, timeout=30).status_code == 404
    assert httpx.get(default.url, timeout=30).status_code == 200
    gone = next(s for s in client.shares(job) if s.id == share.id)
    assert not gone.live and gone.revoked_at is not None
    client.revoke_share(share.id)  # twice: harmless
    client.revoke_share(default)
    with pytest.raises(NotFound):
        client.revoke_share(2_000_000)
    with pytest.raises(NotFound):
        client.share(2_000_000)
    with pytest.raises(ValidationError) as err:
        client.share(job, days=0)
    assert (err.value.status, err.value.field) == (422, "days")


def test_share_label_and_creation_time_are_the_apis(client, job, http):
    """``Share.label`` and ``created_at`` as the API returns them, in the creating
    answer and in the list; no label is None; a label over 200 characters is a 422."""
    named = client.share(job, label="for the review · Q3")
    plain = client.share(job)
    try:
        assert (named.label, plain.label) == ("for the review · Q3", None)
        listed = {s.id: s for s in client.shares(job)}
        raw = {s["id"]: s for s in http.get(f"/jobs/{job.id}/shares").json()}
        for made in (named, plain):
            got = listed[made.id]
            assert got.label == made.label == raw[made.id]["label"]
            assert got.created_at == made.created_at
            assert got.created_at == datetime.fromisoformat(raw[made.id]["created_at"])
        with pytest.raises(ValidationError) as err:
            client.share(job, label="x" * 201)
        assert (err.value.status, err.value.field) == (422, "label")
    finally:
        client.revoke_share(named)
        client.revoke_share(plain)


def test_download_results_matches_the_export(client, job, http, tmp_path):
    csv = http.get(f"/jobs/{job.id}/results", params={"format": "csv", "N": 10}).text
    out = tmp_path / "r.csv"
    client.download_results(job, out, format="csv", N=10)
    assert out.read_bytes() == csv.encode()  # byte for byte (CSV lines end in \r\n)
    buf = io.StringIO()
    client.download_results(job, buf, format="json")
    assert json.loads(buf.getvalue()) == fetch_jsonl(http, job.id)
    missing = tmp_path / "missing.csv"
    with pytest.raises(NotFound):
        client.download_results(2_000_000, missing)
    assert not missing.exists() and list(tmp_path.iterdir()) == [out]  # no temp file left


# --------------------------------------------------------------------------- summary, compare


def test_summary_frame_equals_api_json(client, job, http):
    body = http.get(f"/jobs/{job.id}/summary").json()
    df = client.summary(job)
    assert df.attrs == {"job_id": job.id, "partial": False}
    assert len(df) == len(body["groups"]) == 4
    for (_, row), g in zip(df.iterrows(), body["groups"]):
        for k in ("system", "sigma_w", "N", "estimator", "gamma", "count"):
            assert (_missing(row[k]) and g[k] is None) or _py(row[k]) == g[k], k
        for f, s in g["stats"].items():
            for stat in ("mean", "std", "count"):
                got, want = row[f"{f}_{stat}"], s[stat]
                assert (_missing(got) and want is None) or _py(got) == want, (f, stat)
    long = client.summary(job, long=True)
    assert len(long) == 4 * len(SUMMARY_FIELDS)
    assert list(long.columns) == [
        *("system", "sigma_w", "N", "estimator", "gamma"),
        *("field", "mean", "std", "count"),
    ]
    # an independent oracle: pandas' group-by of the records themselves
    res = client.results(job)
    res["gamma_key"] = res["gamma"].fillna(-1.0)
    grouped = res.groupby(["N", "estimator", "gamma_key"])["rmse_A"].agg(["mean", "count"])
    wide = long[long["field"] == "rmse_A"].assign(gamma_key=lambda d: d["gamma"].fillna(-1.0))
    for _, r in wide.iterrows():
        exp = grouped.loc[(r["N"], r["estimator"], r["gamma_key"])]
        assert r["mean"] == pytest.approx(exp["mean"], rel=1e-12) and r["count"] == exp["count"]


def test_compare_frame_equals_api_json(client, job, http):
    other = client.submit({**SPEC, "seed": 4}, name="client-compare", timeout=150)
    assert other.status == "succeeded"
    params = {"jobs": f"{job.id},{other.id}", "metric": "rmse_A", "by": "N,estimator"}
    body = http.get("/compare", params=params).json()
    df = client.compare([job, other.id], "rmse_A", by=["N", "estimator"])
    assert df.attrs["metric"] == "rmse_A" and df.attrs["by"] == ["N", "estimator"]
    assert list(df.columns) == ["job_id", "N", "estimator", "mean", "std", "count"]
    assert [{k: _py(v) for k, v in r.items()} for r in df.to_dict("records")] == body["rows"]
    assert client.compare_json([job, other], "rmse_A", "N,estimator") == body
    res = pd.concat([client.results(job), client.results(other)], keys=[job.id, other.id])
    res = res.reset_index(level=0, names="job_id")
    oracle = res.groupby(["job_id", "N", "estimator"])["rmse_A"].agg(
        mean="mean", std=lambda x: x.std(ddof=0), count="count"
    )
    for r in body["rows"]:
        exp = oracle.loc[(r["job_id"], r["N"], r["estimator"])]
        assert r["mean"] == pytest.approx(exp["mean"], rel=1e-12)
        assert r["std"] == pytest.approx(exp["std"], rel=1e-9, abs=1e-15)
        assert r["count"] == exp["count"]


# --------------------------------------------------------------------------- jobs


def test_jobs_list_and_idempotent_submit(client, job, http, monkeypatch):
    page = client.jobs(tag="client")
    assert page.total == len(page) >= 1 and job.id in [j.id for j in page]
    api = http.get("/jobs", params={"tag": "client", "status": "succeeded"}).json()
    assert [j.raw for j in client.jobs(tag="client", status="succeeded")] == api["items"]
    assert client.jobs(owner="me", limit=1).limit == 1
    got = client.job(job.id)
    assert got == job and got.raw == http.get(f"/jobs/{job.id}").json()
    assert got.progress.done == got.progress.total and got.finished

    # the progress bar of a real wait, drawn by rich into a buffer
    from rich.console import Console

    screen = io.StringIO()
    console = Console(file=screen, width=120, force_terminal=False)
    monkeypatch.setattr(
        "svrobs_client.client.make_bar",
        lambda job_id, total, status, enabled: RichBar(job_id, total, status, console=console),
    )
    first = client.submit(QUICK, idempotency_key="client-idem", tags="quick")
    assert first.status == "succeeded" and first.tags == ["quick"]
    total = first.progress.total
    assert f"job {first.id} succeeded" in screen.getvalue()
    assert f"{total}/{total} units" in screen.getvalue()
    again = client.submit(QUICK, idempotency_key="client-idem", tags="quick", wait=False)
    assert again.id == first.id
    with pytest.raises(Conflict) as err:
        client.submit({**QUICK, "seed": 99}, idempotency_key="client-idem", wait=False)
    assert err.value.status == 409 and err.value.field == "Idempotency-Key"


def test_cancel_and_paper_preset(stack, client, job):
    """With the worker stopped, a submitted job stays queued and is cancelled; so are
    the jobs of the paper preset. Cancelling a finished job is a 409."""
    stack.stop("worker1", grace=3)
    try:
        queued = client.submit(SPEC, name="to-cancel", wait=False)
        assert queued.status == "queued"
        cancelled = client.cancel(queued)
        assert cancelled.id == queued.id and cancelled.status == "cancelled"
        assert client.job(queued.id).status == "cancelled"
        assert client.wait(queued.id, timeout=5).status == "cancelled"
        assert client.cancel(queued.id).status == "cancelled"
        preset = client.run_paper_preset(scale="reduced", experiments=["E1"])
        assert len(preset) == 1 and preset[0].tags == ["paper-section-6", "E1"]
        assert client.cancel(preset[0]).status == "cancelled"
    finally:
        stack.start_worker()
    with pytest.raises(Conflict) as err:
        client.cancel(job)
    assert err.value.status == 409 and err.value.message == f"job {job.id} already succeeded"


def test_delete(stack, client):
    done = client.submit(QUICK, name="to-delete", timeout=150)
    client.delete(done)
    with pytest.raises(NotFound):
        client.job(done)
    with pytest.raises(NotFound):
        client.results_records(done)
    stack.stop("worker1", grace=3)
    try:
        queued = client.submit(QUICK, name="delete-queued", wait=False)
        with pytest.raises(Conflict):
            client.delete(queued)
        client.cancel(queued)
        client.delete(queued)
        with pytest.raises(NotFound):
            client.job(queued)
    finally:
        stack.start_worker()


# --------------------------------------------------------------------------- report, presets


def test_report_folder(client, job, http, tmp_path):
    page = http.get(f"/jobs/{job.id}/report").text
    rep = client.report(job, tmp_path / "rep")
    assert rep.html == tmp_path / "rep" / "report.html"
    assert rep.html.read_text() == page
    srcs = re.findall(r"src='data:image/png;base64,([^']+)'", page)
    assert len(srcs) == len(rep.figures) >= 1
    for path, src in zip(rep.figures, srcs):
        data = path.read_bytes()
        assert data == base64.b64decode(src) and data.startswith(b"\x89PNG\r\n\x1a\n")
    assert sorted(p.name for p in (tmp_path / "rep").iterdir()) == ["figures", "report.html"]


def test_presets(client, http):
    presets = client.presets()
    assert presets == http.get("/presets").json()
    assert {"paper-stable", "paper-unstable"} <= {p["name"] for p in presets}


# --------------------------------------------------------------------------- schedules


def test_schedules(client, job, http):
    s = client.create_schedule(
        "client-nightly", "0 2 * * *", job, timezone="Europe/Berlin", enabled=False
    )
    assert s.spec_template == job.spec and not s.enabled and s.next_run_at is None
    assert s.raw == http.get(f"/schedules/{s.id}").json()
    assert client.schedule(s.id) == s
    assert s.id in [x.id for x in client.schedules()]
    on = client.enable_schedule(s)
    assert on.enabled and on.next_run_at is not None
    assert on.raw == http.get(f"/schedules/{s.id}").json()
    off = client.disable_schedule(s.id)
    assert not off.enabled and off.next_run_at is None
    renamed = client.update_schedule(s, name="client-nightly-2", tags=["n"])
    assert renamed.name == "client-nightly-2" and renamed.tags == ["n"]
    runs = client.schedule_runs(s)
    assert [r.raw for r in runs] == http.get(f"/schedules/{s.id}/runs").json()
    with pytest.raises(Conflict) as err:
        client.create_schedule("client-nightly-2", "@daily", SPEC)
    assert (err.value.status, err.value.field) == (409, "name")
    with pytest.raises(ValidationError) as err:
        client.create_schedule("bad", "61 * * * *", SPEC)
    assert (err.value.status, err.value.field) == (422, "cron")
    client.delete_schedule(s)
    with pytest.raises(NotFound):
        client.schedule(s.id)
    assert s.seed_policy == "fixed"


def test_schedule_seed_policy_round_trips(client, job, http):
    s = client.create_schedule("client-fresh", "@daily", job, seed_policy="due-time")
    assert s.seed_policy == "due-time" == http.get(f"/schedules/{s.id}").json()["seed_policy"]
    assert client.schedule(s) == s
    fixed = client.update_schedule(s, seed_policy="fixed")
    assert fixed.seed_policy == "fixed" == http.get(f"/schedules/{s.id}").json()["seed_policy"]
    with pytest.raises(ValueError, match="seed_policy must be 'fixed' or 'due-time'"):
        client.create_schedule("client-bad", "@daily", job, seed_policy="random")
    with pytest.raises(ValueError, match="seed_policy"):
        client.update_schedule(s, seed_policy="nightly")
    assert "client-bad" not in [x.name for x in client.schedules()]
    client.delete_schedule(s)


# --------------------------------------------------------------------------- errors, config


def _api_error(response: httpx.Response) -> tuple[int, str | None, str]:
    body = response.json()
    return response.status_code, body["field"], body["detail"]


def test_typed_errors_carry_the_api_body(stack, client, http):
    with stack.client() as raw, Client(stack.base_url, "svr_not-a-key") as bad:
        raw.headers["Authorization"] = "Bearer svr_not-a-key"
        expected = _api_error(raw.get("/jobs"))
        with pytest.raises(AuthError) as err:
            bad.jobs()
    assert expected[0] == 401 and expected[2]
    assert (err.value.status, err.value.field, err.value.message) == expected

    with pytest.raises(NotFound) as err:
        client.job(2_000_000)
    assert (err.value.status, err.value.field, err.value.message) == _api_error(
        http.get("/jobs/2000000")
    )
    assert err.value.message == "job 2000000 not found"

    bad_spec = {**SPEC, "reps": 0}
    with pytest.raises(ValidationError) as err:
        client.submit(bad_spec, wait=False)
    expected = _api_error(http.post("/jobs", json=bad_spec))
    assert (err.value.status, err.value.field, err.value.message) == expected
    assert expected[:2] == (422, "reps")
    assert str(err.value) == f"reps: {expected[2]} (HTTP 422)"

    with pytest.raises(ValidationError) as err:
        client.compare([1], "not-a-field")
    assert (err.value.status, err.value.field) == (422, "metric")
    assert isinstance(err.value, svrobs_client.SvrobsError)

    with Client(f"http://127.0.0.1:{free_port()}", "k", timeout=2) as nowhere:
        with pytest.raises(ConnectionFailed) as err:
            nowhere.jobs()
    assert err.value.status is None and "cannot reach" in err.value.message


def test_config_from_environment_and_file(stack, job, tmp_path, monkeypatch):
    for var in ("SVROBS_URL", "SVROBS_API_KEY"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("SVROBS_CONFIG", str(tmp_path / "none.json"))
    with pytest.raises(ConfigError, match="no API key"):
        Client()
    monkeypatch.setenv("SVROBS_URL", stack.base_url)
    monkeypatch.setenv("SVROBS_API_KEY", stack.key)
    with Client() as c:
        assert c.job(job.id).id == job.id and stack.key not in repr(c)
    monkeypatch.delenv("SVROBS_URL")
    monkeypatch.delenv("SVROBS_API_KEY")
    cfg = tmp_path / "config.json"
    cfg.write_text(json.dumps({"url": stack.base_url + "/", "api_key": stack.key}))
    monkeypatch.setenv("SVROBS_CONFIG", str(cfg))
    with Client() as c:
        assert c.url == stack.base_url and c.job(job.id).id == job.id
    cfg.write_text("{not json")
    with pytest.raises(ConfigError, match="cannot read"):
        Client()


def test_summary_json_pages_through_every_group(client, job, http):
    """In pages of 3 groups the client's summary is the API's in one page; the API
    refuses a page over 10,000 groups, naming limit."""
    whole = http.get(f"/jobs/{job.id}/summary").json()
    assert whole["total"] == len(whole["groups"]) == 4 and whole["offset"] == 0
    paged = client.summary_json(job, page_size=3)
    assert paged["groups"] == whole["groups"] and paged["total"] == 4
    second = http.get(f"/jobs/{job.id}/summary", params={"limit": 3, "offset": 3}).json()
    assert second["groups"] == whole["groups"][3:] and second["limit"] == 3
    r = http.get(f"/jobs/{job.id}/summary", params={"limit": 10_001})
    assert r.status_code == 422 and r.json()["field"] == "limit"
