"""The datasets pages through the app (TestClient), on SQLite and PostgreSQL: the web
upload stores what the API's upload stores (past SVROBS_MAX_BODY_BYTES, under
SVROBS_MAX_DATASET_MB: a 413 naming the file beyond), needs the session's CSRF token,
answers a bad file's error as JSON naming its field with nothing stored; the pages
and the plot data are team-scoped (another team's dataset is a 404); the plot data
are the first rollouts, read without the others; "new job on this dataset", the spec
form on a dataset (the team's datasets listed, a dataset spec kept on submit, errors
beside their fields) and a dataset job's page."""

from __future__ import annotations

import html
import json
import re

import numpy as np
import pytest

from service.db.datasets import load_arrays, load_rollouts
from service.web import spec_form
from svrobs_core import parse_spec
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


def test_plot_data_cuts_long_rollouts_and_many_channels(web, session, make_account):
    """Each plotted rollout is cut to its first PLOTTED_STEPS steps, fewer with many
    channels (at most PLOTTED_VALUES numbers): the plot of a long rollout stays small."""
    acc = make_account()
    csrf = _signed_in(web, acc)
    X, U = files.rollouts(seed=7, lengths=(3000, 10, 2500), n=2, m=1)
    ds = _upload(web, csrf, "long.npz", files.npz_bytes(X, U)).json()
    plot = web.get(f"{ds['url']}/plot-data").json()
    assert plot["steps"] == 2000 and plot["cut"] is True and plot["shown"] == 3
    assert plot["X"] == [X[0][:2001].tolist(), X[1].tolist(), X[2][:2001].tolist()]
    assert plot["U"] == [U[0][:2000].tolist(), U[1].tolist(), U[2][:2000].tolist()]
    X, U = files.rollouts(seed=8, lengths=(1000, 12), n=40, m=10)
    ds = _upload(web, csrf, "wide.npz", files.npz_bytes(X, U)).json()
    plot = web.get(f"{ds['url']}/plot-data").json()
    assert plot["steps"] == 200_000 // (5 * 50) == 800 and plot["cut"] is True
    assert plot["X"][0] == X[0][:801].tolist() and plot["U"][1] == U[1].tolist()
    assert sum(np.size(a) for a in plot["X"] + plot["U"]) <= 200_000


def test_load_rollouts_reads_the_arrays_across_chunks(client, session, make_account):
    """The first rollouts, whole or cut, equal load_arrays' (which reads every chunk),
    for rollouts that span the stored chunks' boundaries."""
    acc = make_account()
    X, U = files.rollouts(seed=9, lengths=(40_000, 30_000, 50_000, 7), n=2, m=1)
    r = client.post(
        f"{API}/datasets",
        files={"file": ("big.npz", files.npz_bytes(X, U))},
        data={"name": "big"},
        headers=acc.headers,
    )
    assert r.status_code == 201, r.text
    Xa, Ua, _ = load_arrays(session, r.json()["id"])
    for count, cut in ((3, None), (4, 35_000), (2, 1), (9, 0)):
        Xs, Us = load_rollouts(session, r.json()["id"], count, max_steps=cut)
        k = min(count, 4)
        want_X = [x if cut is None else x[: cut + 1] for x in Xa[:k]]
        want_U = [u if cut is None else u[:cut] for u in Ua[:k]]
        assert len(Xs) == k and all(np.array_equal(a, b) for a, b in zip(Xs, want_X))
        assert all(np.array_equal(a, b) for a, b in zip(Us, want_U))


def test_a_dataset_jobs_page_has_the_validation_card_and_no_table_2(web, make_account):
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
    assert "table2-card" not in page.text  # RMSE needs the true system: no Table 2
    sim = web.post(
        f"{API}/jobs",
        json={"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10], "reps": 1},
        headers={"Authorization": f"Bearer {acc.key}"},
    ).json()
    sim_page = web.get(f"/jobs/{sim['id']}").text
    assert "validation-card" not in sim_page and "table2-card" in sim_page


def _posted(values: dict, **edits) -> dict:
    """The spec form as the browser posts it ({name: [values]}) from its values, then
    ``edits`` ({input name: text}) typed in."""
    form, lists = spec_form.as_posted(values)
    form.update(edits)
    return {**{k: [v] for k, v in form.items()}, **lists}


def test_the_spec_form_on_a_dataset_keeps_a_dataset_spec(web, build_client, make_account):
    """The form's dataset field lists the team's datasets (not another team's), "new
    job on this dataset" chooses it, and its fields submit a dataset spec; the fields
    a dataset job does not take are not sent; every error is beside its field."""
    acc, other = make_account(), make_account()
    csrf = _signed_in(web, acc)
    X, U = files.rollouts(seed=9, lengths=(12,) * 10, n=2, m=1)
    first = _upload(web, csrf, "a.csv", files.csv_bytes(X, U)).json()
    ds = _upload(web, csrf, "b.csv", files.csv_bytes(X, U)).json()
    theirs, _ = build_client(SECRET_KEY="pages-secret-0123456789")
    other_csrf = (sign_in(theirs, other.key), csrf_of(theirs.get("/datasets").text))[1]
    foreign = _upload(theirs, other_csrf, "c.csv", files.csv_bytes(X, U)).json()

    page = web.get(f"/jobs/new?dataset={ds['id']}").text
    select = re.search(r'<select name="f.dataset"[^>]*>(.*?)</select>', page, re.S).group(1)
    options = dict(re.findall(r'<option value="(\d*)"[^>]*>([^<]*)</option>', select))
    assert set(options) == {"", str(first["id"]), str(ds["id"])}  # not the other team's
    assert f'<option value="{ds["id"]}" selected>' in select and str(foreign["id"]) not in options
    assert re.search(r'id="field-systems"[^>]* hidden', page)  # a simulated job's field
    assert not re.search(r'id="field-holdout"[^>]* hidden', page)

    starter = json.loads(
        html.unescape(re.search(r'<textarea[^>]*id="spec"[^>]*>([^<]*)<', page).group(1))
    )
    data = _posted(spec_form.values_of(starter), **{"f.reps": "2"})
    data.update(csrf_token=csrf, source="form", name="on b")
    r = web.post("/jobs/new", data=data, follow_redirects=False)
    assert r.status_code == 303, r.text[-2000:]
    job = web.get(f"{API}{r.headers['location']}").json()
    assert job["spec"] == parse_spec({**starter, "reps": 2}).to_dict()
    assert job["spec"]["dataset"] == ds["id"] and "systems" not in job["spec"]

    # errors of a dataset spec, each beside its field (σ_w is the dataset's level field)
    bad = _posted(
        spec_form.values_of(starter),
        **{"f.dataset_sigma_w": "-1", "f.C": "[[1, 0", "f.bounds_method": "bootstrap"},
    )
    bad.update(csrf_token=csrf, source="form")
    r = web.post("/jobs/new", data=bad)
    assert r.status_code == 422
    beside = dict(re.findall(r'id="err-([\w.-]+)"><p><code>[^<]*</code>: ([^<]*)</p>', r.text))
    assert set(beside) == {"dataset_sigma_w", "C", "bounds_method"}, beside
    assert (
        beside["C"].startswith("not valid JSON") and beside["dataset_sigma_w"] == "must be &gt;= 0"
    )
    assert "self-normalized" in html.unescape(beside["bounds_method"])
    assert "3 errors to fix" in r.text and 'value="-1"' in r.text  # as typed
    # a dataset the team does not have: named on the dataset field
    bad = _posted(spec_form.values_of({**starter, "dataset": foreign["id"]}))
    bad.update(csrf_token=csrf, source="form")
    r = web.post("/jobs/new", data=bad)
    assert r.status_code == 422 and f"no dataset {foreign['id']} in your team" in r.text
    assert re.search(r'id="err-dataset"', r.text)


def test_the_spec_form_shows_every_error_against_the_datasets_shape(web, make_account):
    """N beyond the rollouts left after the holdout and a C with the wrong number of
    columns: both errors at once, each beside its field (each needs the dataset's
    shape, so the parser alone cannot find them)."""
    acc = make_account()
    csrf = _signed_in(web, acc)
    X, U = files.rollouts(seed=9, lengths=(12,) * 10, n=2, m=1)  # 10 rollouts, n = 2
    ds = _upload(web, csrf, "a.csv", files.csv_bytes(X, U)).json()
    page = web.get(f"/jobs/new?dataset={ds['id']}").text
    starter = json.loads(
        html.unescape(re.search(r'<textarea[^>]*id="spec"[^>]*>([^<]*)<', page).group(1))
    )
    edits = {"f.N": "5, 10, 30", "f.holdout": "4", "f.C": "[[1, 0, 0]]"}
    bad = _posted(spec_form.values_of(starter), **edits)
    bad.update(csrf_token=csrf, source="form")
    r = web.post("/jobs/new", data=bad)
    assert r.status_code == 422
    beside = dict(re.findall(r'id="err-([\w.-]+)"><p><code>[^<]*</code>: ([^<]*)</p>', r.text))
    assert set(beside) == {"N", "C"}, beside
    assert "N = 30 rollouts, but the dataset has 6 for training" in beside["N"]
    assert "must have 2 columns" in beside["C"]
    assert "2 errors to fix" in r.text
    assert 'value="5, 10, 30"' in r.text  # as typed
    # the spec as the JSON view sends it: the same two errors
    spec = {**starter, "N": [5, 10, 30], "holdout": 4, "C": [[1, 0, 0]]}
    r = web.post("/jobs/new", data={"csrf_token": csrf, "source": "json", "spec": json.dumps(spec)})
    assert r.status_code == 422 and "2 errors to fix" in r.text
    # one fixed: the other alone
    spec["N"] = [5]
    r = web.post("/jobs/new", data={"csrf_token": csrf, "source": "json", "spec": json.dumps(spec)})
    assert r.status_code == 422 and "1 error to fix" in r.text and "must have 2 columns" in r.text
    assert web.get(f"{API}/jobs", headers=acc.headers).json()["total"] == 0
