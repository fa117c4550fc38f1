"""A cell's page (/results/cell) through the app (TestClient): linked from every row
of the results grid, its matrices' entries are the API's record for that cell (OLS's
γ null included), under the glossary's names and units; a missing cell or another
team's job is a 404 page, a bad γ a 422."""

from __future__ import annotations

import html
import re
from urllib.parse import parse_qsl, urlsplit

import pytest

from svrobs_core.records import FIELD_GLOSSARY, MATRIX_FIELDS
from tests.service.svc_fakes import run_job_units

from .helpers import sign_in

API = "/api/v1"
SPEC = {
    "systems": ["paper-stable"],
    "sigma_w": [1.0],
    "N": [20],
    "reps": 2,
    "gamma": [0.05],
    "estimators": ["ols", "svr"],
    "stages": ["estimate", "bounds", "gain"],
    "seed": 5,
}
LINK = re.compile(r'<a class="cell-link" href="([^"]+)"')
FIGURE = re.compile(r'<figure class="matrix" data-field="(\w+)".*?</figure>', re.S)
ENTRY = re.compile(r'data-i="(\d+)" data-j="(\d+)" data-value="([^"]*)"')


@pytest.fixture
def web(build_client):
    return build_client(SECRET_KEY="pages-secret-0123456789")[0]


@pytest.fixture
def done(web, session, make_account):
    acc = make_account()
    r = web.post(f"{API}/jobs", json=SPEC, headers=acc.headers)
    assert r.status_code == 202, r.text
    run_job_units(session, r.json()["id"])
    sign_in(web, acc.key)
    return acc, r.json()["id"]


def matrices_of(text: str) -> dict[str, list[list[float | None]]]:
    """The matrices a cell page shows: field -> rows of the entries' data-value."""
    out = {}
    for m in FIGURE.finditer(text):
        cells = {(int(i), int(j)): (float(v) if v else None) for i, j, v in ENTRY.findall(m[0])}
        n, k = max(i for i, _ in cells) + 1, max(j for _, j in cells) + 1
        out[m[1]] = [[cells[i, j] for j in range(k)] for i in range(n)]
    return out


def test_every_row_links_its_cell_page_with_the_apis_matrices(web, done):
    acc, jid = done
    grid = web.get(f"/results?job={jid}&sort=-rmse_A")
    links = [html.unescape(h) for h in LINK.findall(grid.text)]
    assert len(links) == 2 * 2  # reps x (ols + svr at one γ)
    for href in links:
        q = dict(parse_qsl(urlsplit(href).query))
        api = web.get(
            f"{API}/jobs/{jid}/results",
            params={k: q[k] for k in ("system", "sigma_w", "N", "estimator", "gamma", "rep")},
            headers=acc.headers,
        ).json()
        assert api["total"] == 1, href
        want = api["items"][0]
        page = web.get(href)
        assert page.status_code == 200, page.text
        shown = matrices_of(page.text)
        assert set(shown) == {f for f in MATRIX_FIELDS if want[f] is not None} >= {"A_hat"}
        for field, rows in shown.items():
            assert rows == want[field], field
            label, unit, _ = FIELD_GLOSSARY[field]
            fig = re.search(
                rf'<figure class="matrix" data-field="{field}".*?</figure>', page.text, re.S
            )
            assert f"<strong>{label}</strong>" in fig[0] and unit in fig[0]
        scalar = re.search(r'<tr data-field="rmse_A">.*?data-value="([^"]*)"', page.text)
        assert float(scalar[1]) == want["rmse_A"]
        assert "sort=-rmse_A" in html.unescape(page.text)  # back to the same view
    ols = [h for h in links if "estimator=ols" in h]
    assert ols and all("gamma=null" in h for h in ols)


def test_missing_cell_other_team_and_bad_gamma(web, done, make_account):
    acc, jid = done
    base = f"/results/cell?job={jid}&system=paper-stable&sigma_w=1.0&N=20&estimator=svr"
    assert web.get(f"{base}&gamma=0.05&rep=0").status_code == 200
    assert web.get(f"{base}&gamma=0.05&rep=7").status_code == 404
    assert web.get(f"{base}&gamma=0.5&rep=0").status_code == 404
    bad = web.get(f"{base}&gamma=abc&rep=0")
    assert bad.status_code == 422 and "gamma" in bad.text
    other = make_account()
    sign_in(web, other.key)
    assert web.get(f"{base}&gamma=0.05&rep=0").status_code == 404
