"""What a page does with its query string, through the app (TestClient):

* a form's empty field is no value (the runs filter sends ``at=`` and ``hide=`` empty);
* a bad or missing query value, and a path with no page, is the HTML error page with
  the API's status (422 naming the parameter, 404), a title and a language; under
  /api/v1 the same request keeps its JSON;
* ``/compare?jobs=1,2`` (the API's comma form) picks both jobs; a grid coordinate is
  not a metric there;
* the runs table past its last page shows the last page, and a metric column without
  its N says so;
* the database down or busy, and a bug, are the error page too (503, 500), in plain
  words and with no traceback; the API keeps its JSON.
"""

from __future__ import annotations

import html
import re

import pytest
from sqlalchemy.exc import OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout

from service.db import job_queries
from tests.service.svc_fakes import stored_job
from tests.service.svc_helpers import TINY_SPEC

from .helpers import sign_in

API = "/api/v1"


@pytest.fixture
def web(build_client):
    return build_client(SECRET_KEY="query-errors-secret-0123456789")[0]


def _signed_in_jobs(web, session, make_account, seeds):
    acc = make_account()
    ids = [stored_job(web, session, acc, {**TINY_SPEC, "seed": s}) for s in seeds]
    sign_in(web, acc.key)
    return acc, ids


@pytest.fixture
def done(web, session, make_account):
    """A signed-in team with two jobs whose cells are stored."""
    return _signed_in_jobs(web, session, make_account, (5, 6))


@pytest.fixture
def one(web, session, make_account):
    """A signed-in team with one job whose cells are stored."""
    acc, (a,) = _signed_in_jobs(web, session, make_account, (5,))
    return acc, a


def _error_page(r, status: int, *texts: str) -> str:
    """The page's message, after checking that ``r`` is the HTML error page."""
    assert r.status_code == status, (r.status_code, r.text[:300])
    assert r.headers["content-type"].startswith("text/html"), r.text[:300]
    assert re.search(r'<html lang="en">', r.text)
    title = {404: "Not found", 422: "Invalid input", 500: "Server error"}
    title = {**title, 503: "Service unavailable"}[status]
    assert f"<title>{title} · svrobs</title>" in r.text
    assert f"<h1>{status} · {title}</h1>" in r.text
    message = html.unescape(re.search(r'<p class="error-message">(.*?)</p>', r.text, re.S)[1])
    for text in texts:
        assert text in message, message
    return message


def test_the_runs_filter_as_the_form_sends_it(web, done):
    """Every field of the filter form is sent, the empty ones as ``name=``."""
    _, (a, b) = done
    r = web.get("/jobs?q=&status=&tag=&owner=&metric=&at=&sort=&hide=")
    assert r.status_code == 200, r.text[:300]
    assert f'id="job-{a}"' in r.text and f'id="job-{b}"' in r.text
    r = web.get("/jobs/rows?q=&status=succeeded&tag=&owner=&metric=&at=&page=")
    assert r.status_code == 200 and f'id="job-{a}"' in r.text
    with_metric = web.get("/jobs?q=&status=&metric=rmse_A&at=10&sort=&hide=")
    assert with_metric.status_code == 200 and "RMSE Â at N = 10" in with_metric.text
    # an empty field elsewhere: the page's default
    assert web.get(f"/results?job={a}&page=").status_code == 200
    assert web.get("/schedules/new?job=").status_code == 200
    assert web.get("/jobs/new?dataset=&preset=").status_code == 200


@pytest.mark.parametrize(
    ("path", "texts"),
    [
        ("/jobs?page=abc", ["page: "]),
        ("/jobs?page=0", ["page: ", "greater than or equal to 1"]),
        ("/jobs?at=abc", ["at: "]),
        ("/jobs/rows?at=0", ["at: "]),
        ("/results?job=abc", ["job: "]),
        ("/results?job={a}&page=-1", ["page: "]),
        ("/results/cell?job={a}", ["system: ", "sigma_w: ", "N: ", "estimator: ", "rep: "]),
        ("/jobs/new?dataset=abc", ["dataset: "]),
        ("/schedules/new?job=abc", ["job: "]),
        ("/jobs/delete?jobs=abc", ["jobs"]),
        ("/compare?jobs={a},abc", ["jobs: "]),
        ("/jobs/{a}/share?created=abc", ["created: "]),
    ],
)
def test_a_bad_query_is_the_error_page_naming_the_parameter(web, one, path, texts):
    _, a = one
    _error_page(web.get(path.format(a=a)), 422, *texts)


@pytest.mark.parametrize("path", ["/jobs/abc", "/jobs/{a}/zzz", "/nope", "/results/cells"])
def test_a_path_with_no_page_is_the_404_page(web, one, path):
    _, a = one
    path = path.format(a=a)
    _error_page(web.get(path), 404, f"There is no page at {path}")


def test_the_api_keeps_its_json(web, one):
    acc, a = one
    r = web.get(f"{API}/nope", headers=acc.headers)
    assert r.status_code == 404 and r.json() == {"detail": "Not Found", "field": None}
    r = web.get(f"{API}/jobs/{a}/results", params={"N": ""}, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "N"
    r = web.post(f"{API}/jobs", json={**TINY_SPEC, "name": 5}, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "name", r.text
    assert r.json()["errors"][0]["field"] == "name"


def test_compare_takes_the_apis_comma_form(web, done):
    acc, (a, b) = done
    listed = web.get(f"/compare?jobs={a}&jobs={b}&metric=rmse_A")
    commas = web.get(f"/compare?jobs={a},{b}&metric=rmse_A")
    assert commas.status_code == 200, commas.text[:500]
    picked = re.compile(r'name="jobs" value="(\d+)" checked')
    assert set(picked.findall(commas.text)) == {str(a), str(b)}
    table = re.compile(r'<table[^>]*id="compare-table".*?</table>', re.S)
    assert table.search(commas.text)[0] == table.search(listed.text)[0]
    api = web.get(
        f"{API}/compare", params={"jobs": f"{a},{b}", "metric": "rmse_A"}, headers=acc.headers
    ).json()
    assert len(api["rows"]) > 0 and api["jobs"] == [a, b]


@pytest.mark.parametrize("coordinate", ["sigma_w", "N", "gamma", "rep"])
def test_compare_refuses_a_grid_coordinate_as_the_metric(web, one, coordinate):
    _, a = one
    r = web.get(f"/compare?jobs={a}&metric={coordinate}")
    _error_page(r, 422, f"metric: {coordinate} is a grid coordinate, not a metric")


def test_the_runs_table_past_its_last_page_shows_the_last_page(web, done):
    _, (a, b) = done
    r = web.get("/jobs?page=99")
    assert r.status_code == 200
    assert f'id="job-{a}"' in r.text and f'id="job-{b}"' in r.text
    assert "No jobs" not in r.text and "page 99" not in r.text
    rows = web.get("/jobs/rows?page=99")
    assert f'id="job-{a}"' in rows.text


def test_a_metric_column_without_its_n_says_what_is_missing(web, done):
    r = web.get("/jobs?metric=rmse_A")
    assert r.status_code == 200
    note = re.search(r'<p[^>]*id="metric-note"[^>]*>(.*?)</p>', r.text, re.S)
    assert note and "needs an N" in note[1] and "rmse_A" in note[1], r.text[-3000:]
    assert 'aria-describedby="metric-note"' in r.text  # the "at N" box points to it
    r = web.get("/jobs?at=10")
    note = re.search(r'<p[^>]*id="metric-note"[^>]*>(.*?)</p>', r.text, re.S)
    assert note and "Pick a metric" in note[1]
    assert 'id="metric-note"' not in web.get("/jobs?metric=rmse_A&at=10").text


def _raising(exc: Exception):
    def read(*args, **kwargs):
        raise exc

    return read


DOWN = OperationalError("SELECT", {}, Exception("server closed the connection"))


@pytest.mark.parametrize(
    ("exc", "status", "text", "retry"),
    [
        (DOWN, 503, "The database is unavailable. Try again in a few seconds.", "5"),
        (PoolTimeout("QueuePool limit reached"), 503, "The database is busy.", "1"),
        (RuntimeError("a bug"), 500, "Something went wrong on the server", None),
    ],
)
def test_an_error_of_the_server_is_the_error_page(web, one, monkeypatch, exc, status, text, retry):
    """A page (and the runs table htmx polls) whose database read fails is the error
    page in plain words, never the API's JSON or the exception's text."""
    acc, _ = one
    monkeypatch.setattr(job_queries, "job_page", _raising(exc))
    for path in ("/jobs", "/jobs/rows", "/compare"):
        r = web.get(path)
        message = _error_page(r, status, text)
        assert r.headers.get("retry-after") == retry
        assert str(exc.args[0]) not in r.text and "Traceback" not in r.text, message
    api = web.get(f"{API}/jobs", headers=acc.headers)  # the API's answer stays JSON
    assert api.status_code == status and "detail" in api.json()


def test_the_runs_table_pager_reaches_the_first_and_last_pages(
    web, session, make_account, monkeypatch
):
    """Past the second page the pager links the first and the last page too (a team with
    1,000 jobs has 40 pages); "newer" and "older" only in the default order."""
    from service.web.pages import jobs as jobs_page

    monkeypatch.setattr(jobs_page, "PAGE_SIZE", 1)
    _signed_in_jobs(web, session, make_account, (5, 6, 7, 8, 9))
    pager = re.compile(r'<a (?:rel="\w+" )?href="/jobs\?([^"]*)" id="jobs-(\w+)">([^<]*)</a>')
    links = {k: (html.unescape(q), t) for q, k, t in pager.findall(web.get("/jobs?page=3").text)}
    assert links == {
        "first": ("page=1", "« newest"),
        "prev": ("page=2", "← newer"),
        "next": ("page=4", "older →"),
        "last": ("page=5", "oldest »"),
    }
    page = web.get("/jobs?sort=name&page=2").text
    texts = {k: t for _, k, t in pager.findall(page)}
    assert texts == {"prev": "← previous", "next": "next →", "last": "last page »"}
