"""Summaries of values near the double range's ends (docs/spec.md#summaries): the
running job's summary aggregated in the database and the stored one of a
finished job give finite numbers or null with a note, never an error.

Oracle: mean and std computed here with fractions (exact rational arithmetic)
over the values written."""

from __future__ import annotations

import math
from fractions import Fraction

import pytest

from svrobs_core.records import OVERFLOW_NOTE
from tests.service.svc_fakes import fake_records
from tests.service.svc_helpers import SMALL_SPEC

API = "/api/v1"


def _exact(values):
    xs = [Fraction(v) for v in values]
    m = sum(xs) / len(xs)
    var = sum((x - m) ** 2 for x in xs) / len(xs)
    k = 1024 if var > 1 else -1024  # var may be beyond the double range either way
    return float(m), math.sqrt(float(var / Fraction(2) ** k)) * 2.0 ** (k // 2)


def _extreme_records(spec, payload):
    """The fake unit's records with J_exact set to huge values and rmse_A to tiny
    ones (and H_A so large that its std overflows)."""
    recs = fake_records(spec, payload)
    for i, r in enumerate(recs):
        r["J_exact"] = (1.0 + 0.25 * (i % 3)) * 1e200
        r["rmse_A"] = (1 + i % 2) * 1e-170
        r["H_A"] = 1.7e308 if i % 2 else -1.7e308
    return recs


def test_huge_and_tiny_values_summarise_without_error(client, session, make_account):
    from service.db import jobs, units

    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    uids = jobs.unit_ids_of_job(session, jid, pending_only=False)
    written = []
    for k, uid in enumerate(uids):
        spec, payload = units.start_unit(session, uid, "w", 60, max_attempts=0)
        recs = _extreme_records(spec, payload)
        written += recs
        units.complete_unit(session, uid, recs)
        session.commit()
        if k == 0:  # running: aggregated in the database
            partial = client.get(f"{API}/jobs/{jid}/summary", headers=acc.headers)
            assert partial.status_code == 200 and partial.json()["partial"] is True
            _check(partial.json()["groups"], written)
    final = client.get(f"{API}/jobs/{jid}/summary", headers=acc.headers)
    assert final.status_code == 200 and final.json()["partial"] is False
    _check(final.json()["groups"], written)


def _check(groups, written):
    by_key = {}
    for r in written:
        key = (r["system"], r["sigma_w"], r["N"], r["estimator"], r["gamma"])
        by_key.setdefault(key, []).append(r)
    assert groups
    for g in groups:
        rows = by_key[(g["system"], g["sigma_w"], g["N"], g["estimator"], g["gamma"])]
        for f in ("J_exact", "rmse_A"):
            mean, std = _exact([r[f] for r in rows])
            assert g["stats"][f]["mean"] == pytest.approx(mean, rel=1e-12), f
            # squared deviations below ~1e-300 underflow to 0 (numpy and SQL alike)
            assert g["stats"][f]["std"] == pytest.approx(std, rel=1e-9, abs=1e-150), f
        h = g["stats"]["H_A"]
        if len({r["H_A"] for r in rows}) > 1:  # +-1.7e308: std 1.7e308 fits, the sums do not
            mean, std = _exact([r["H_A"] for r in rows])
            assert h["count"] == len(rows)
            if h["std"] is None:
                assert OVERFLOW_NOTE in h["note"]
            else:
                assert h["std"] == pytest.approx(std, rel=1e-9)
                assert h["mean"] == pytest.approx(mean, rel=1e-9, abs=1e295)


def test_compare_pools_huge_and_far_apart_values_as_the_exact_mean_and_std(
    client, session, make_account
):
    """``GET /compare`` on values whose squares overflow (J_exact near 1e200) and on
    groups whose means are far apart (J_star 3e6 in one estimator's groups, 1e-3 in
    the other's: one shift for the whole job cancelled to a std of 0.06 where it is 0),
    while the job runs (from its rows) and once it has finished (from its summaries),
    by several fields: the exact mean and std of each group's values (Fraction)."""
    from service.db import jobs, units

    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    uids = jobs.unit_ids_of_job(session, jid, pending_only=False)
    written: list[dict] = []
    for k, uid in enumerate(uids):
        spec, payload = units.start_unit(session, uid, "w", 60, max_attempts=0)
        recs = _extreme_records(spec, payload)
        for i, r in enumerate(recs):
            r["J_star"] = 3e6 if r["estimator"] == "ols" else 1e-3 * (1 + i % 5)
        written += recs
        units.complete_unit(session, uid, recs)
        session.commit()
        if k == 0 or k == len(uids) - 1:  # running (rows), then finished (summaries)
            for by in ("N", "estimator", "rep", "system,sigma_w,N,estimator,gamma"):
                for metric in ("J_exact", "J_star"):
                    _check_compare(client, acc, jid, metric, by, written)


def _check_compare(client, acc, jid, metric, by, written):
    params = {"jobs": str(jid), "metric": metric, "by": by, "limit": 1000}
    r = client.get(f"{API}/compare", params=params, headers=acc.headers)
    assert r.status_code == 200, r.text
    fields = by.split(",")
    groups: dict[tuple, list[float]] = {}
    for rec in written:
        groups.setdefault(tuple(rec[f] for f in fields), []).append(rec[metric])
    rows = r.json()["rows"]
    assert len(rows) == len(groups), (metric, by)
    for row in rows:
        values = groups[tuple(row[f] for f in fields)]
        mean, std = _exact(values)
        assert row["count"] == len(values)
        assert row["mean"] == pytest.approx(mean, rel=1e-12), (metric, by, row)
        # a group of one value repeated: its std is 0 up to the last bit of its mean
        assert row["std"] == pytest.approx(std, rel=1e-9, abs=4 * math.ulp(abs(mean))), (
            metric,
            by,
            row,
        )
