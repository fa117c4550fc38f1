"""The datasets pages through the app (TestClient), on SQLite and PostgreSQL: the web
upload stores what the API's upload stores (past SVROBS_MAX_BODY_BYTES, under
SVROBS_MAX_DATASET_MB: a 413 naming the file beyond), needs the session's CSRF token,
answers a bad file's error as JSON naming its field with nothing stored; the pages
and the plot data are team-scoped (another team's dataset is a 404); the plot data
are the first rollouts, read without the others; "new job on this dataset" and a
dataset job's page."""

from __future__ import annotations

import html
import json
import re

import numpy as np
import pytest

from service.db.datasets import load_arrays, load_rollouts
from tests.datasets import files
from tests.service.test_service_datasets import counts

from .helpers import csrf_of, sign_in

API = "/api/v1"


@pytest.fixture
def web(build_client):
    return build_client(
        SECRET_KEY="pages-secret-0123456789", MAX_BODY_BYTES=4096, MAX_DATASET_MB=1
    )[0]


def _signed_in(web, acc) -> str:
    assert sign_in(web, acc.key).status_code == 303
    return csrf_of(web.get("/datasets").text)


def _upload(web, csrf, name: str, data: bytes, **fields):
    return web.post(
        "/datasets/upload",
        files={"file": (name, data)},
        data={"name": "runs", "csrf_token": csrf, **fields},
        headers={"X-CSRF-Token": csrf} if csrf else {},
    )


def test_web_upload_stores_what_the_api_stores(web, session, make_account):
    acc = make_account()
    csrf = _signed_in(web, acc)
    X, U = files.rollouts(seed=5, lengths=(60,) * 6)
    data = files.csv_bytes(X, U)
    assert 4096 < len(data) < 2**20  # over the body limit, under the dataset limit
    r = _upload(web, csrf, "runs.csv", data, sample_time="0.5")
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["url"] == f"/datasets/{body['id']}"
    stored = web.get(f"{API}/datasets/{body['id']}").json()  # the session reads the API
    assert (stored["rollouts"], stored["n"], stored["m"], stored["sample_time"]) == (6, 3, 2, 0.5)
    X2, U2, _ = load_arrays(session, body["id"])
    assert all(np.array_equal(a, b) for a, b in zip(X + U, X2 + U2))
    page = web.get("/datasets")
    assert page.status_code == 200 and f'data-dataset="{body["id"]}"' in page.text


def test_web_upload_refusals_store_nothing(web, session, make_account):
    acc = make_account()
    csrf = _signed_in(web, acc)
    before = counts(session)
    r = _upload(web, None, "runs.csv", b"rollout,k,x1\n0,0,1\n0,1,2\n")
    assert r.status_code == 403
    r = _upload(web, csrf, "runs.csv", b"rollout,k,x1\n0,0,1\n0,1,zz\n")
    assert r.status_code == 422 and r.json()["field"] == "file"
    assert "'zz' is not a number" in r.json()["detail"]
    r = _upload(web, csrf, "runs.csv", b"rollout,k,x1\n0,0,1\n0,1,2\n", sample_time="-1")
    assert r.status_code == 422 and r.json()["field"] == "sample_time"
    big = b"rollout,k,x1\n" + b"0,0,1\n" * (2**20 // 6 + 10)
    r = _upload(web, csrf, "big.csv", big)
    assert r.status_code == 413 and r.json()["field"] == "file"
    assert counts(session) == before


def test_pages_and_plot_data_are_the_teams(web, build_client, session, make_account):
    acc, other = make_account(), make_account()
    csrf = _signed_in(web, acc)
    X, U = files.rollouts(seed=6, lengths=(5, 9, 3, 7, 4, 8, 6), n=2, m=1)
    ds = _upload(web, csrf, "r.npz", files.npz_bytes(X, U), sample_time="0.1").json()
    page = web.get(ds["url"])
    assert page.status_code == 200
    assert 'id="fact-rollouts">7<' in page.text and 'href="/jobs/new?dataset=' in page.text
    assert 'id="ex-lambda-min"' in page.text
    plot = web.get(f"{ds['url']}/plot-data").json()
    assert plot["shown"] == 5 and plot["rollouts"] == 7 and plot["sample_time"] == 0.1
    assert plot["X"] == [x.tolist() for x in X[:5]] and plot["U"] == [u.tolist() for u in U[:5]]
    Xs, Us = load_rollouts(session, ds["id"], 3)
    assert all(np.array_equal(a, b) for a, b in zip(Xs + Us, X[:3] + U[:3]))
    form = web.get(f"/jobs/new?dataset={ds['id']}")
    text = re.search(r'<textarea[^>]*id="spec"[^>]*>([^<]*)<', form.text).group(1)
    spec = json.loads(html.unescape(text))
    assert spec["dataset"] == ds["id"] and spec["holdout"] == 1 and spec["N"] == [1, 3, 6]
    theirs, _ = build_client(SECRET_KEY="pages-secret-0123456789")
    sign_in(theirs, other.key)
    for path in (ds["url"], f"{ds['url']}/plot-data", f"/jobs/new?dataset={ds['id']}"):
        assert theirs.get(path).status_code == 404, path
    assert theirs.get("/datasets").text.count("data-dataset=") == 0


def test_a_dataset_jobs_page_has_the_validation_card(web, make_account):
    acc = make_account()
    csrf = _signed_in(web, acc)
    X, U = files.rollouts(seed=8, lengths=(10,) * 5, n=2, m=1)
    ds = _upload(web, csrf, "r.csv", files.csv_bytes(X, U)).json()
    job = web.post(
        f"{API}/jobs",
        json={"dataset": ds["id"], "N": [3], "holdout": 2, "reps": 1},
        headers={"Authorization": f"Bearer {acc.key}"},
    ).json()
    page = web.get(f"/jobs/{job['id']}")
    assert page.status_code == 200
    assert f'data-validation-url="/api/v1/jobs/{job["id"]}/validation"' in page.text
    assert "/static/validation.js" in page.text
    assert web.get(f"{API}/jobs/{job['id']}/validation").status_code == 200  # by the session
    sim = web.post(
        f"{API}/jobs",
        json={"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10], "reps": 1},
        headers={"Authorization": f"Bearer {acc.key}"},
    ).json()
    assert "validation-card" not in web.get(f"/jobs/{sim['id']}").text
