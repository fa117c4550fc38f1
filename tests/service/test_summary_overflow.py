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
