"""Responses and stored bytes are bounded (docs/deploy.md#bounded-responses): a JSON page
of a job with large matrices is shortened to SVROBS_MAX_PAGE_MATRIX_ENTRIES and says
where the next one starts, a stream reads a bounded number of matrix entries at a
time, and a job whose records would be too large to store is refused with a 422
naming SVROBS_MAX_JOB_STORED_MB. The job is a real 20x20 system stored as a worker
stores it; the oracle of the pages is the whole JSON lines export."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.db import jobs, units
from service.db import result_queries as rq
from svrobs_core.parsing import parse_spec
from svrobs_core.records import MATRIX_FIELDS
from svrobs_core.runner import run_unit_result
from svrobs_lab import results

API = "/api/v1"
N_STATES = 20
# per record (estimate, bounds): A_hat and radii_A are 20 x 20, B_hat and radii_B 20 x 1
ENTRIES = 2 * N_STATES * N_STATES + 2 * N_STATES
CAP = 3 * ENTRIES + 7  # three records per page


def _system() -> dict:
    A = (0.5 * np.eye(N_STATES) + 0.02 * np.eye(N_STATES, k=1)).tolist()
    return {"name": "big20", "A": A, "B": np.ones((N_STATES, 1)).tolist()}


SPEC = {
    "systems": [_system()],
    "sigma_w": [0.5],
    "N": [30],
    "reps": 7,
    "estimators": ["ols"],
    "stages": ["estimate", "bounds"],
    "seed": 3,
}


@pytest.fixture
def big_job(build_client, session, make_account):
    client, _ = build_client(MAX_PAGE_MATRIX_ENTRIES=CAP)
    acc = make_account()
    r = client.post(f"{API}/jobs", json=SPEC, headers=acc.headers)
    assert r.status_code == 202, r.text
    jid = r.json()["id"]
    for uid in jobs.unit_ids_of_job(session, jid):
        spec_dict, payload = units.start_unit(session, uid, "w", 60, max_attempts=0)
        units.complete_unit(session, uid, run_unit_result(parse_spec(spec_dict), payload))
        session.commit()
    return client, acc, jid


def _entries(rec: dict) -> int:
    return sum(np.asarray(rec[f], dtype=float).size for f in MATRIX_FIELDS if rec[f] is not None)


def test_a_page_holds_at_most_the_cap_and_the_pages_are_the_export(big_job):
    client, acc, jid = big_job
    url = f"{API}/jobs/{jid}/results"
    export = client.get(url, params={"format": "jsonl"}, headers=acc.headers)
    want = [json.loads(line) for line in export.text.splitlines()]
    assert len(want) == 7 and {_entries(r) for r in want} == {ENTRIES}
    got, offset, pages = [], 0, []
    while offset is not None:
        page = client.get(url, params={"limit": 100, "offset": offset}, headers=acc.headers)
        assert page.status_code == 200, page.text
        body = page.json()
        assert body["limit"] == 3 and body["total"] == 7 and body["offset"] == offset
        assert sum(_entries(r) for r in body["items"]) <= CAP
        got += body["items"]
        pages.append(len(body["items"]))
        offset = body["next_offset"]
    assert pages == [3, 3, 1] and got == want


def test_a_page_under_the_cap_keeps_its_limit(big_job):
    client, acc, jid = big_job
    body = client.get(
        f"{API}/jobs/{jid}/results", params={"limit": 2, "offset": 6}, headers=acc.headers
    ).json()
    assert body["limit"] == 2 and len(body["items"]) == 1 and body["next_offset"] is None
    body = client.get(f"{API}/jobs/{jid}/results", params={"limit": 2}, headers=acc.headers).json()
    assert body["limit"] == 2 and body["next_offset"] == 2


def test_a_stream_reads_a_bounded_number_of_entries_at_a_time(big_job, monkeypatch):
    client, acc, jid = big_job
    url = f"{API}/jobs/{jid}/results"
    whole = client.get(url, params={"format": "jsonl"}, headers=acc.headers).content
    sizes = []
    chunks = rq.row_chunks

    def recording(session, query, size):
        for chunk in chunks(session, query, size):
            sizes.append(len(chunk))
            yield chunk

    monkeypatch.setattr(rq, "row_chunks", recording)
    monkeypatch.setattr(results, "STREAM_ENTRIES", 2 * ENTRIES)
    for fmt in ("jsonl", "csv"):
        sizes.clear()
        r = client.get(url, params={"format": fmt}, headers=acc.headers)
        assert r.status_code == 200
        assert sizes == [2, 2, 2, 1], fmt  # two records' entries a read
        if fmt == "jsonl":
            assert r.content == whole


def test_a_job_too_large_to_store_is_refused_naming_the_setting(build_client, make_account):
    client, _ = build_client(MAX_JOB_STORED_MB=1)
    acc = make_account()
    # 7 * 40 cells of 840 entries: about 1.9 MB of matrices
    r = client.post(
        f"{API}/jobs",
        json={**SPEC, "reps": 40, "N": [30, 40, 50, 60, 70, 80, 90]},
        headers=acc.headers,
    )
    assert r.status_code == 422, r.text
    body = r.json()
    assert "SVROBS_MAX_JOB_STORED_MB" in body["detail"] and "MB" in body["detail"]
    assert body["field"] in ("reps", "N")
    small = client.post(f"{API}/jobs", json=SPEC, headers=acc.headers)
    assert small.status_code == 202, small.text
