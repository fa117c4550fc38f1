"""Input the API refuses with a 422 naming it, never a 500 or a silent other answer:

* a model export's cell coordinate N or rep beyond a 32-bit column (SQLite's driver
  overflows past 64 bits, PostgreSQL binds ``::INTEGER``), in the text and JSON form;
* a coordinate given twice in the JSON form of a cell (as in the text form);
* a range filter's number not written in plain ASCII decimal (the rule of ``N`` and
  ``sigma_w``): ``٣``, full-width ``１``, ``1_0``, `` 1 ``;
* a share link's label with a NUL or another control character;
* more range filters than MAX_RANGE_FILTERS (SQLite refused a WHERE of 1,000 ANDs:
  a 503 on a JSON page, a CSV cut short after its header).
"""

from __future__ import annotations

import json

import pytest
from sqlalchemy import func, select

from service.db.models import ShareLink
from service.db.result_queries import MAX_RANGE_FILTERS
from tests.service.svc_fakes import stored_job
from tests.service.svc_helpers import TINY_SPEC

API = "/api/v1"
RANGE = "must be from -2147483648 to 2147483647"


@pytest.fixture
def done(client, session, make_account):
    """A team's job with its cells stored (paper-stable, N=10, ols, rep 0 and 1)."""
    acc = make_account()
    return acc, stored_job(client, session, acc, TINY_SPEC)


def _model(client, acc, jid, cell):
    return client.get(f"{API}/jobs/{jid}/model", params={"cell": cell}, headers=acc.headers)


def _refused(r, field: str) -> str:
    assert r.status_code == 422, r.text
    assert r.json()["field"] == field, r.text
    return r.json()["detail"]


@pytest.mark.parametrize(
    "cell",
    [
        "N=99999999999999999999,estimator=ols,rep=0",
        "N=10,estimator=ols,rep=99999999999999999999",
        "N=3000000000",
        "N=2147483648",
        "rep=-2147483649",
        "N=-9223372036854775809",
        "N=" + "9" * 1500,
        '{"N": 99999999999999999999}',
        '{"N": 10, "rep": 3000000000}',
    ],
)
def test_a_cell_coordinate_beyond_32_bits_is_a_422_naming_the_cell(client, done, cell):
    acc, jid = done
    detail = _refused(_model(client, acc, jid, cell), "cell")
    assert RANGE in detail and detail.startswith(("N ", "rep ")), detail


def test_a_cell_coordinate_at_the_32_bit_edge_is_looked_up(client, done):
    acc, jid = done
    for cell in ("N=2147483647", '{"rep": -2147483648}'):
        assert _refused(_model(client, acc, jid, cell), "cell").startswith("no cell of job")
    ok = _model(client, acc, jid, "N=10,estimator=ols,rep=0")
    assert ok.status_code == 200 and ok.json()["N"] == 10


@pytest.mark.parametrize(
    "cell",
    [
        '{"N": 99, "estimator": "ols", "rep": 0, "N": 10}',
        '{"rep": 1, "N": 10, "rep": 0}',
        '{"estimator": "svr", "rep": 0, "estimator": "ols"}',
    ],
)
def test_a_json_cell_naming_a_coordinate_twice_is_a_422(client, done, cell):
    acc, jid = done
    key = next(iter(json.loads(cell)))
    # the text form's message: neither value is taken
    assert _refused(_model(client, acc, jid, cell), "cell") == f"{key} given twice"
    one = dict(json.loads(cell))
    assert _model(client, acc, jid, json.dumps(one)).status_code == 200


@pytest.mark.parametrize("value", ["٣", "１", "1_0", " 1 ", "+1", "0x1", "1e", "1.5f"])
@pytest.mark.parametrize("name", ["N_gte", "rmse_A_lt", "r_A_gt"])
def test_a_range_filter_takes_only_a_plain_ascii_number(client, done, name, value):
    acc, jid = done
    for fmt in ("json", "csv"):
        r = client.get(
            f"{API}/jobs/{jid}/results",
            params={name: value, "format": fmt},
            headers=acc.headers,
        )
        assert _refused(r, name) == "must be a number"


def test_a_range_filter_in_plain_ascii_still_filters(client, done):
    acc, jid = done
    for params, total in (({"N_gte": "10"}, 2), ({"N_gt": "1e1"}, 0), ({"rep_lt": ".5"}, 1)):
        r = client.get(f"{API}/jobs/{jid}/results", params=params, headers=acc.headers)
        assert r.status_code == 200 and r.json()["total"] == total, (params, r.text)
    for value in ("1e999", "-inf", "NaN"):
        r = client.get(f"{API}/jobs/{jid}/results", params={"N_lt": value}, headers=acc.headers)
        assert _refused(r, "N_lt") == "must be finite"


def test_more_range_filters_than_the_cap_is_a_422_naming_the_first_past_it(client, done):
    acc, jid = done
    many = [("rmse_A_lt", str(10 + i)) for i in range(1100)]
    for fmt in ("json", "csv", "jsonl"):
        r = client.get(
            f"{API}/jobs/{jid}/results", params=[*many, ("format", fmt)], headers=acc.headers
        )
        assert "at most 100 range filters" in _refused(r, "rmse_A_lt"), fmt
    r = client.get(
        f"{API}/jobs/{jid}/results", params=[*many[:MAX_RANGE_FILTERS]], headers=acc.headers
    )
    assert r.status_code == 200 and r.json()["total"] == 2, r.text


@pytest.mark.parametrize(
    "label, message",
    [
        ("a\x00b", "NUL"),
        ("a\nb\x07", "printable"),
        ("tab\there", "printable"),
        ("\ud800", "surrogate"),
    ],
)
def test_a_share_label_is_printable_text(client, session, done, label, message):
    acc, jid = done
    r = client.post(
        f"{API}/jobs/{jid}/shares",
        content=json.dumps({"label": label}),
        headers={**acc.headers, "Content-Type": "application/json"},
    )
    assert message in _refused(r, "label")
    assert session.scalar(select(func.count(ShareLink.id))) == 0
    ok = client.post(f"{API}/jobs/{jid}/shares", json={"label": "for Ada"}, headers=acc.headers)
    assert ok.status_code == 201 and ok.json()["label"] == "for Ada"
