"""Only validation errors are 4xx: a fault inside the core during a submission is a
JSON 500 that carries no internals, and its traceback is in the log."""

from __future__ import annotations

import logging

import pytest

from svrobs_core.errors import DimensionError
from svrobs_core.spec import ExperimentSpec
from tests.service.svc_helpers import SMALL_SPEC

API = "/api/v1"
FAULT = "injected fault 4f2a9c"
ROUTES = [("/jobs", SMALL_SPEC), ("/presets/paper-section-6/run", {"scale": "reduced"})]


def _fault(exc_type):
    def to_dict(self):  # stands in for ExperimentSpec.to_dict, called by every submission
        raise DimensionError("A", FAULT) if exc_type is DimensionError else exc_type(FAULT)

    return to_dict


@pytest.mark.parametrize("route, body", ROUTES)
# a DimensionError is a ValueError of the core that a parsed spec never causes: a bug too
@pytest.mark.parametrize(
    "exc_type", [ZeroDivisionError, ValueError, TypeError, KeyError, DimensionError]
)
def test_core_fault_is_a_logged_500_without_internals(
    client, publisher, make_account, monkeypatch, caplog, route, body, exc_type
):
    acc = make_account()
    with monkeypatch.context() as m, caplog.at_level(logging.ERROR, "service.api.errors"):
        m.setattr(ExperimentSpec, "to_dict", _fault(exc_type))
        r = client.post(f"{API}{route}", json=body, headers=acc.headers)

    # a bug is not the user's mistake: not a 422, and nothing of the exception leaks
    assert r.status_code == 500
    assert r.headers["content-type"].startswith("application/json")
    assert r.headers["x-content-type-options"] == "nosniff"  # as on every response
    assert r.headers["referrer-policy"] == "same-origin"
    assert r.json() == {"detail": "internal error", "field": None}
    for leak in (FAULT, exc_type.__name__, "Traceback", "to_dict", ".py"):
        assert leak not in r.text

    # ... but the log has the whole story
    logged = [x for x in caplog.records if x.name == "service.api.errors"]
    assert len(logged) == 1 and logged[0].levelno == logging.ERROR
    assert logged[0].exc_info[0] is exc_type
    assert f"POST {API}{route}" in logged[0].getMessage()
    assert "Traceback (most recent call last)" in caplog.text and FAULT in caplog.text
    assert "in to_dict" in caplog.text  # down to the frame that raised

    # the failed request stored and published nothing
    assert client.get(f"{API}/jobs", headers=acc.headers).json()["total"] == 0
    assert publisher.calls == []


def test_spec_errors_stay_422_naming_the_field(client, make_account, caplog):
    acc = make_account()
    with caplog.at_level(logging.ERROR, "service.api.errors"):
        r = client.post(f"{API}/jobs", json={**SMALL_SPEC, "gamma": [-1]}, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "gamma[0]"
    assert not [x for x in caplog.records if x.name == "service.api.errors"]


def test_a_misspelt_field_of_a_body_names_the_field_it_is_close_to(client, make_account):
    """``POST /jobs`` with ``sigmaw`` (the CLI prints the detail: ``error: invalid spec:
    sigmaw: unknown field (did you mean 'sigma_w'?)``); a name close to none of the body's
    fields, or a server-owned one, stays "unknown field"; a schedule's body likewise."""
    acc = make_account()
    spec = {k: v for k, v in SMALL_SPEC.items() if k != "sigma_w"}
    schedule = {"name": "n", "cron": "0 2 * * *", "spec_template": SMALL_SPEC}
    cases = [
        ("/jobs", {**spec, "sigmaw": SMALL_SPEC["sigma_w"]}, "sigmaw", "sigma_w"),
        ("/jobs", {**SMALL_SPEC, "tag": ["x"]}, "tag", "tags"),
        ("/jobs", {**SMALL_SPEC, "bogus": 1}, "bogus", None),
        ("/jobs", {**SMALL_SPEC, "status": "done"}, "status", None),
        ("/schedules", {**schedule, "timezon": "UTC"}, "timezon", "timezone"),
    ]
    for path, body, field, close in cases:
        r = client.post(f"{API}{path}", json=body, headers=acc.headers)
        assert r.status_code == 422, r.text
        hint = f" (did you mean '{close}'?)" if close else ""
        assert (r.json()["field"], r.json()["detail"]) == (field, "unknown field" + hint)
