"""The pages take their query strings by the API's rules, so bad input is a 422 naming
the parameter (the error page, or the grid's own error in place), never a 500:

* a NUL character in any query parameter (PostgreSQL text cannot hold it);
* a grid coordinate N or rep beyond a 32-bit column (the API's results filters'
  bounds) and a number not written in plain ASCII decimal, in a filter or a range;
* a dataset id beyond 32 bits on the new-job form;
* a share link's label that is not printable text.

An empty field of a filter form is no filter, as before.
"""

from __future__ import annotations

import re

import pytest
from sqlalchemy import func, select

from service.db.models import ShareLink
from tests.service.svc_fakes import stored_job
from tests.service.svc_helpers import TINY_SPEC

from .helpers import csrf_of, sign_in

RANGE = "must be from -2147483648 to 2147483647"
TOO_BIG = "9" * 20


@pytest.fixture
def web(build_client):
    return build_client(SECRET_KEY="bounds-secret-0123456789")[0]


@pytest.fixture
def done(web, session, make_account):
    """A signed-in team with a job whose cells are stored (paper-stable, N=10, rep 0, 1)."""
    acc = make_account()
    jid = stored_job(web, session, acc, TINY_SPEC)
    sign_in(web, acc.key)
    return acc, jid


def _error_page(r, text: str) -> None:
    assert r.status_code == 422, (r.status_code, r.text[:300])
    assert "text/html" in r.headers["content-type"]
    assert text in r.text, r.text[:2000]


def _cell(jid: int, **kw) -> dict:
    return {
        "job": jid,
        "system": "paper-stable",
        "sigma_w": "1.0",
        "N": "10",
        "estimator": "ols",
        "gamma": "null",
        "rep": "0",
        **kw,
    }


@pytest.mark.parametrize(
    "path, params, field",
    [
        ("/jobs", {"q": "\x00"}, "q"),
        ("/jobs", {"tag": "a\x00"}, "tag"),
        ("/jobs", {"owner": "\x00"}, "owner"),
        ("/jobs/rows", {"q": "x\x00y"}, "q"),
        ("/results", {"system": "\x00"}, "system"),
        ("/results/rows", {"estimator": "ols\x00"}, "estimator"),
        ("/results/cell", {"system": "\x00"}, "system"),
    ],
)
def test_a_nul_in_a_query_parameter_is_a_422_page(web, done, path, params, field):
    _, jid = done
    if path.startswith("/results"):
        params = _cell(jid, **params) if path == "/results/cell" else {"job": jid, **params}
    _error_page(web.get(path, params=params), f"{field}: must not contain NUL")


@pytest.mark.parametrize(
    "query, message",
    [
        (f"N={TOO_BIG}", f"N: {RANGE}"),
        ("N=3000000000", f"N: {RANGE}"),
        ("rep=-9223372036854775809", f"rep: {RANGE}"),
        ("rep=2147483648", f"rep: {RANGE}"),
        ("N=٣", "N: must be an integer"),
        ("sigma_w=１", "sigma_w: must be a decimal number"),
    ],
)
def test_a_grid_filter_beyond_32_bits_or_not_ascii_is_a_422(web, done, query, message):
    _, jid = done
    _error_page(web.get(f"/results?job={jid}&{query}"), message)
    rows = web.get(f"/results/rows?job={jid}&{query}")
    assert rows.status_code in (200, 422) and message in rows.text, rows.text[:500]


@pytest.mark.parametrize("value", ["١", "１", "1_0", " 1 ", "0x1"])
def test_a_range_bound_is_a_plain_ascii_number(web, done, value):
    _, jid = done
    q = {"job": jid, "rf": "rmse_A", "rmin": "", "rmax": value}
    _error_page(web.get("/results", params=q), "rmse_A_lt: must be a number")
    rows = web.get("/results/rows", params=q)  # the grid shows it in its place
    assert rows.status_code == 200 and "rmse_A_lt: must be a number" in rows.text


def _total(page) -> int:
    assert page.status_code == 200, page.text[:300]
    return int(re.search(r"<span>(\d+) records?", page.text).group(1))


def test_empty_fields_of_the_filter_form_are_no_filter(web, done):
    _, jid = done
    form = {"job": jid, "N": "", "rep": "", "sigma_w": "", "rf": "", "rmin": "", "rmax": ""}
    assert _total(web.get("/results", params=form)) == 2
    assert _total(web.get("/results", params={**form, "N": "10", "rep": "1"})) == 1
    edge = {**form, "N": "2147483647", "rep": "-2147483648"}
    assert _total(web.get("/results", params=edge)) == 0


@pytest.mark.parametrize("dataset", [TOO_BIG, "3000000000", "2147483648", "0"])
def test_a_dataset_id_beyond_32_bits_on_the_new_job_form_is_refused(web, done, dataset):
    r = web.get("/jobs/new", params={"dataset": dataset})
    assert r.status_code == 422, (r.status_code, r.text[:300])
    missing = web.get("/jobs/new", params={"dataset": "2147483647"})
    assert missing.status_code == 404


@pytest.mark.parametrize("label", ["a\x00b", "a\nb\x07"])
def test_a_share_label_made_on_the_page_is_printable_text(web, session, done, label):
    _, jid = done
    page = web.get(f"/jobs/{jid}/share")
    token = csrf_of(page.text)
    r = web.post(
        f"/jobs/{jid}/share",
        data={"csrf_token": token, "days": "7", "label": label},
        follow_redirects=False,
    )
    _error_page(r, "label: must be printable text")
    assert session.scalar(select(func.count(ShareLink.id))) == 0
    ok = web.post(
        f"/jobs/{jid}/share",
        data={"csrf_token": token, "days": "7", "label": "for Ada"},
        follow_redirects=False,
    )
    assert ok.status_code == 303 and re.search(r"created=\d+", ok.headers["location"])


def test_a_form_body_over_the_limit_is_the_error_page_and_the_apis_json(build_client, make_account):
    """SVROBS_MAX_BODY_BYTES refuses a body before any route: a page's form gets the
    web's error page (413, HTML, the security headers), the API JSON naming the limit."""
    web = build_client(SECRET_KEY="bounds-secret-0123456789", MAX_BODY_BYTES=2_000)[0]
    acc = make_account()
    sign_in(web, acc.key)
    form = {"csrf_token": csrf_of(web.get("/jobs/new").text), "spec": "x" * 5_000}
    page = web.post("/jobs/new", data=form)
    assert page.status_code == 413 and "text/html" in page.headers["content-type"]
    assert "Too large" in page.text and "2000 bytes" in page.text, page.text[:2000]
    assert page.headers["x-content-type-options"] == "nosniff"
    api = web.post("/api/v1/jobs", content=b"{" + b" " * 5_000 + b"}", headers=acc.headers)
    assert api.status_code == 413 and "2000 bytes" in api.json()["detail"]
    assert api.headers["x-content-type-options"] == "nosniff"
