"""Extreme but valid specs (hypothesis): ``run-local`` finishes, writes strict JSON
(no NaN, no infinity), and every true certificate holds when re-checked exactly.

Generated (tiny grids, 1-2 states): tiny sigma_u, long rollouts of unstable
systems, tiny and huge gamma, huge M, sigma_w = 0 and huge, N just above the
dimension, final data, nearly singular C, marginal systems (rho(A) = 1), huge
x0_std, every bounds_method and stage chain.

Oracles, in exact rational arithmetic (fractions) on the record's own numbers:
a self-normalized box that certifies is first recomputed in 60-digit mpmath
from the simulated data (up to 200 samples) and must agree to 1e-6;
``stable_certified`` true needs rho(M) < 1 for the nonnegative M = |A_hat| + R
(paper: |(1+gamma) A~| + r_A), decided by the leading principal minors of
I - M (all positive iff rho(M) < 1 for M >= 0); ``certified`` true needs
g(L) < 1. With sigma_w = 0 the self-normalized box holds the truth for sure
(no noise; ridge: when ||theta_i|| <= S), so there ``stable_certified`` true
needs rho(A) < 1 and ``certified`` true rho(A - L C) < 1, both decided by the
Jury test in rationals.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from fractions import Fraction
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from svrobs_cli.local import run_local
from svrobs_core import estimators as est
from svrobs_core.rollouts import gram_data
from svrobs_core.seeding import seed_key
from svrobs_core.systems import resolve_system
from tests.core.exact_boxes import exact_box

# 250 generated specs per `make test`; `make test-faults` runs 2,000
# (SVROBS_PROPERTY_EXAMPLES), with the soak tests.
EXAMPLES = int(os.environ.get("SVROBS_PROPERTY_EXAMPLES", "250"))


def _fr(x) -> Fraction:
    return Fraction(float(x))


def _det(M):
    n = len(M)
    if n == 1:
        return M[0][0]
    return M[0][0] * M[1][1] - M[0][1] * M[1][0]


def _nonneg_rho_below_one(M) -> bool:
    """rho(M) < 1 for an entrywise nonnegative M (n <= 2): I - M is a nonsingular
    M-matrix iff its leading principal minors are positive."""
    n = len(M)
    I_M = [[(1 if i == j else 0) - M[i][j] for j in range(n)] for i in range(n)]
    return all(_det([row[:k] for row in I_M[:k]]) > 0 for k in range(1, n + 1))


def _schur(M) -> bool:
    """rho(M) < 1 for any real M (n <= 2): |m| < 1, or Jury's |det| < 1, |tr| < 1 + det."""
    if len(M) == 1:
        return abs(M[0][0]) < 1
    det, tr = _det(M), M[0][0] + M[1][1]
    return abs(det) < 1 and abs(tr) < 1 + det


def _strict(text: str):
    def refuse(token):
        raise AssertionError(f"non-finite JSON number {token}")

    return json.loads(text, parse_constant=refuse)


# ---------------------------------------------------------------------------
# strategies
# ---------------------------------------------------------------------------
BOUNDS = ["estimate", "bounds"]
GAIN = [*BOUNDS, "gain"]
STAGE_CHAINS = [BOUNDS, BOUNDS, GAIN, GAIN, GAIN, [*GAIN, "cost", "cost_bound"]]


@st.composite
def systems(draw):
    n = draw(st.sampled_from([1, 1, 2]))
    m = draw(st.sampled_from([1, 1, 2]))
    kind = draw(st.sampled_from(["stable", "unstable", "marginal", "fastslow"]))
    if kind == "marginal":
        A = [[1.0]] if n == 1 else draw(st.sampled_from([[[1.0, 0.0], [0.0, 0.5]],
                                                          [[0.5, 0.5], [0.25, 0.75]]]))  # fmt: skip
    elif kind == "fastslow" and n == 2:
        a, b = 1.0 + draw(st.sampled_from([1e-4, 0.025])), 0.025
        A = [[a, b], [b, a]]
    else:
        rho = draw(st.floats(0.0, 0.99)) if kind == "stable" else draw(st.floats(1.001, 1.6))
        raw = [[draw(st.floats(-1.0, 1.0)) for _ in range(n)] for _ in range(n)]
        s = max(abs(np.linalg.eigvals(np.array(raw))).max(), 1e-3)
        A = (np.array(raw) * (rho / s)).tolist()
    B = [[draw(st.sampled_from([0.0, 1e-9, 0.5, 1.0, -2.0])) for _ in range(m)] for _ in range(n)]
    if all(v == 0 for row in B for v in row):
        B[0][0] = 1.0
    sigma_v = draw(st.sampled_from([0.1, 0.1, 1e-6, 100.0]))
    C = None
    if n == 2 and draw(st.integers(0, 3)) == 0:
        eps = draw(st.sampled_from([1e-8, 1e-12]))
        C = draw(st.sampled_from([[[1.0, 0.0], [0.0, eps]], [[1.0, eps]]]))
    elif draw(st.integers(0, 5)) == 0:
        sigma_v = 0.0  # C = I
    out = {"name": f"s{kind}", "A": A, "B": B, "sigma_u": draw(st.sampled_from([1e-8, 1e-3, 1.0])),
           "sigma_v": sigma_v}  # fmt: skip
    if C is not None:
        out["C"] = C
    return out


@st.composite
def specs(draw):
    system = draw(systems())
    n, m = len(system["A"]), len(system["B"][0])
    d = n + m
    method = draw(st.sampled_from(["paper", "self-normalized", "self-normalized", "bootstrap"]))
    long_run = draw(st.integers(0, 9)) == 0
    spec = {
        "systems": [system],
        "sigma_w": [draw(st.sampled_from([0.0, 0.0, 1e-18, 1e-3, 1.0, 1e3, 1e100]))],
        "N": [draw(st.sampled_from([1, d, d + 1, 5]))],
        "T0": draw(st.sampled_from([300, 1000])) if long_run else draw(st.sampled_from([2, 3, 11])),
        "reps": draw(st.integers(1, 2)),
        "estimators": draw(
            st.lists(
                st.sampled_from(["ols", "svr", "shrunk-ols"]), min_size=1, max_size=3, unique=True
            )
        ),  # fmt: skip
        "gamma": draw(
            st.lists(
                st.sampled_from([1e-300, 1e-12, 0.05, 1e6, 1e100, 1e300]),
                min_size=1,
                max_size=2,
                unique=True,
            )
        ),  # fmt: skip
        "loss_scale": draw(st.sampled_from(["sum", "mean"])),
        "data": draw(st.sampled_from(["all", "final"])),
        "M": draw(st.sampled_from([1e-3, 1.1, 1e6, 1e300])),
        "delta": draw(st.sampled_from([1e-9, 0.05, 0.5])),
        "bounds_method": method,
        "stages": draw(st.sampled_from(STAGE_CHAINS)),
        "horizon": draw(st.sampled_from([1, 5])),
        "mc_reps": 0,
        "margin": draw(st.sampled_from([0.0, 0.01, 0.99])),
        "x0_std": draw(st.sampled_from([0.0, 0.0, 1.0, 1e100])),
        "seed": draw(st.integers(0, 2**63 - 1)),
    }
    if "C" in system:  # a general C: the gain design solves a cone program per cell
        spec["reps"] = 1
    if method == "self-normalized":
        spec["S"] = draw(st.sampled_from([None, 1e-6, 1e6]))
        spec["lambda0"] = draw(st.sampled_from([1e-6, 1.0, 1e6]))
    if method == "bootstrap":
        spec["boot_reps"] = draw(st.integers(2, 4))
        spec["boot_sigma_w"] = draw(st.sampled_from(["estimate", "spec"]))
    return spec


# ---------------------------------------------------------------------------
# the exact re-checks
# ---------------------------------------------------------------------------
def _centre_and_radius(r, spec):
    """(rational centre, rational radius matrix) of the record's certificate box."""
    A = [[_fr(v) for v in row] for row in r["A_hat"]]
    n = len(A)
    if spec["bounds_method"] == "paper":
        one_g = 1 + (_fr(r["gamma"]) if r["gamma"] is not None else 0)
        centre = [[one_g * v for v in row] for row in A]
        R = [[_fr(r["r_A"])] * n for _ in range(n)]
    else:
        centre = A
        R = [[_fr(v) for v in row] for row in r["radii_A"]]
    return centre, R


def _check_radii_with_mpmath(r, spec, system):
    if r["N0"] > 200:
        return
    event("a certifying self-normalized box recomputed in mpmath")
    _, _, Z, _ = gram_data(
        resolve_system(system),
        r["sigma_w"],
        r["N"],
        spec["T0"],
        seed=spec["seed"],
        keys=[seed_key(0, 0, r["N"], r["rep"])],
        data=spec["data"],
        x0_std=spec["x0_std"],
        keep_data=True,
    )
    lam, shrink = 0.0, 0.0
    if r["estimator"] == "svr":
        lam = float(est.ridge_parameters([r["gamma"]], r["N0"], spec["loss_scale"])[0])
    elif r["estimator"] == "shrunk-ols":
        shrink = r["gamma"]
    theta = np.concatenate([np.array(r["A_hat"]), np.array(r["B_hat"])], axis=1)
    S = spec.get("S") or math.sqrt(2) * spec["M"]
    ex = exact_box(Z[0], theta, sigma_w=r["sigma_w"], delta=spec["delta"], lam=lam, S=S,
                   lambda0=spec.get("lambda0", 1.0), shrink=shrink)  # fmt: skip
    R = np.concatenate([np.array(r["radii_A"]), np.array(r["radii_B"])], axis=1)
    assert np.allclose(R, ex.R, rtol=1e-6, atol=0), (R, ex.R)


def _check_record(r, spec, system):
    n = len(system["A"])
    C = system.get("C") or np.eye(n).tolist()
    if (r["stable_certified"] or r.get("certified")) and spec["bounds_method"] == "self-normalized":
        _check_radii_with_mpmath(r, spec, system)
    if r["stable_certified"]:
        event(f"stable_certified true ({spec['bounds_method']})")
        centre, R = _centre_and_radius(r, spec)
        M = [[abs(centre[i][j]) + R[i][j] for j in range(n)] for i in range(n)]
        assert _nonneg_rho_below_one(M), r
    if r.get("certified"):
        event(f"certified true ({spec['bounds_method']})")
        centre, R = _centre_and_radius(r, spec)
        L = [[_fr(v) for v in row] for row in r["L"]]
        p = len(C)
        rows = []
        for i in range(n):
            c = [centre[i][j] - sum(L[i][k] * _fr(C[k][j]) for k in range(p)) for j in range(n)]
            rows.append(sum(abs(c[j]) + R[i][j] for j in range(n)))
        assert max(rows) < 1, r
    if spec["sigma_w"][0] == 0 and spec["bounds_method"] == "self-normalized":
        theta = np.concatenate([np.array(system["A"]), np.array(system["B"])], axis=1)
        S = spec.get("S") or math.sqrt(2) * spec["M"]
        if r["estimator"] == "svr" and np.linalg.norm(theta, axis=1).max() > S:
            return  # the ridge box assumes ||theta_i|| <= S
        A_true = [[_fr(v) for v in row] for row in system["A"]]
        if r["stable_certified"] or r.get("certified"):
            event("a certificate at sigma_w = 0, checked against the truth")
        if r["stable_certified"]:
            assert _schur(A_true), r
        if r.get("certified"):
            L = [[_fr(v) for v in row] for row in r["L"]]
            F = [[A_true[i][j] - sum(L[i][k] * _fr(C[k][j]) for k in range(len(C)))
                  for j in range(n)] for i in range(n)]  # fmt: skip
            assert _schur(F), r


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(spec=specs())
def test_extreme_valid_specs_run_and_their_certificates_hold(spec):
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        try:
            res = run_local(spec, out, quiet=True)  # raises (a traceback: exit 1) on any failure
        except Exception as exc:
            exc.add_note(f"spec: {json.dumps(spec)}")
            raise
        lines = (out / "records.jsonl").read_text().splitlines()
        assert res["records"] == len(lines) > 0
        _strict((out / "summary.json").read_text())
        for line in lines:
            _check_record(_strict(line), spec, spec["systems"][0])
