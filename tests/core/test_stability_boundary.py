"""Quantities that exist only for a Schur-stable matrix, on the unit circle
(docs/science.md#62-stationary-j_stationary, svrobs_core.norms.schur_stable).

The systems below have rho(A) = 1 exactly, shown in exact rational arithmetic
(fractions), while numpy's and python-control's eigenvalues put their spectral
radius a few ulps below 1; scipy's solve_discrete_lyapunov finds the Stein
operator singular (an error, or a "solution" of size 1/u). Their stationary cost and their H-infinity norms are
infinite, so J_stationary, J_bound and the SLS quantities are null with a note.
"""

from __future__ import annotations

import warnings
from fractions import Fraction

import control
import numpy as np
import pytest
import scipy.linalg as sla

from svrobs_core import parse_spec, run_spec
from svrobs_core.cost import stationary_cost
from svrobs_core.norms import (
    REASON_BOUNDARY,
    UNIT_CIRCLE_TOL,
    h2_norm,
    hinf_norm,
    schur_stable,
    stability_reason,
)

# det 1 and |trace| < 2: a complex pair on the unit circle (dyadic entries, exact)
ROTATION = [[-2.0, -2.0], [0.75, 0.25]]
# rows summing to 1 exactly, nonnegative: eigenvalue 1 = the largest row sum
STOCHASTIC = [[0.5, 0.5], [0.875, 0.125]]
B = [[1.0], [0.5]]


def _exact_rho_is_one(A) -> bool:
    """rho(A) = 1 in exact arithmetic, for the two kinds of 2 x 2 matrices above."""
    (a, b), (c, d) = ([Fraction(x) for x in row] for row in A)
    det, tr = a * d - b * c, a + d
    if det == 1 and abs(tr) < 2:  # complex pair with |lambda|^2 = det
        return True
    rows = [a + b, c + d]
    nonneg = min(a, b, c, d) >= 0
    return nonneg and rows == [1, 1]  # Perron root of a stochastic matrix


@pytest.mark.parametrize("A", [ROTATION, STOCHASTIC], ids=["rotation", "stochastic"])
def test_the_oracles_see_the_boundary_only_in_exact_arithmetic(A):
    assert _exact_rho_is_one(A)
    An = np.array(A)
    assert np.abs(np.linalg.eigvals(An)).max() < 1.0  # rounded below the circle
    sys = control.ss(An, np.array(B), np.eye(2), np.zeros((2, 1)), True)
    assert np.abs(sys.poles()).max() < 1.0
    with warnings.catch_warnings():  # scipy's LinAlgWarning: rcond ~ 1e-17
        warnings.simplefilter("ignore")
        try:  # no stationary covariance: singular, or a solution of size ~1/u
            assert np.trace(sla.solve_discrete_lyapunov(An, np.eye(2))) > 1e15
        except np.linalg.LinAlgError:
            pass
    assert not schur_stable(np.abs(np.linalg.eigvals(An)).max())


@pytest.mark.parametrize("A", [ROTATION, STOCHASTIC], ids=["rotation", "stochastic"])
def test_norms_and_stationary_cost_of_a_boundary_system_are_null(A):
    An, Bn = np.array(A), np.array(B)
    h2, why = h2_norm(An, Bn, np.eye(2), return_reason=True)
    assert np.isnan(h2) and why == REASON_BOUNDARY
    hinf, why = hinf_norm(An, Bn, np.eye(2), return_reason=True)
    assert np.isnan(hinf) and why == REASON_BOUNDARY
    noise = dict(sigma_u=1.0, sigma_w=0.1, sigma_v=0.1)
    J, why = stationary_cost(
        An, Bn, 0.5 * An, Bn, L=np.zeros((2, 2)), C=None, **noise, return_reason=True
    )
    assert np.isnan(J) and why == REASON_BOUNDARY


def test_the_boundary_is_one_rule_on_the_computed_radius():
    rho = np.array([0.5, 1 - 2 * UNIT_CIRCLE_TOL, 1 - UNIT_CIRCLE_TOL / 2, 1.0, 1.5, np.nan])
    assert schur_stable(rho).tolist() == [True, True, False, False, False, False]
    reasons = stability_reason(None, rho)
    assert reasons.tolist() == [
        None,
        None,
        REASON_BOUNDARY,
        "unstable",
        "unstable",
        "non-finite input",
    ]


@pytest.mark.parametrize("A", [ROTATION, STOCHASTIC], ids=["rotation", "stochastic"])
def test_records_of_a_boundary_system_give_no_stationary_cost_or_bound(A):
    """A true system with rho(A) = 1: from the rounded radius, J_stationary was
    2.7e11 (stochastic) and J_bound 8.5e16 (rotation); they are null with a note,
    and the SLS program is not run (its F needs the infinite H-infinity norms)."""
    spec = parse_spec(
        {
            "systems": [{"name": "boundary", "A": A, "B": B}],
            "sigma_w": [0.1],
            "N": [20],
            "reps": 1,
            "estimators": ["ols"],
            "stages": ["estimate", "bounds", "gain", "cost", "cost_bound", "sls"],
            "horizon": 50,
        }
    )
    records = [r for batch in run_spec(spec) for r in batch]
    assert records
    for r in records:
        assert r["J_exact"] is not None  # the finite horizon needs no stability
        for f in ("J_stationary", "J_bound", "delta_J", "J_opt", "J_opt_bound"):
            assert r[f] is None, (f, r[f])
        assert r["sls_status"] == "not_run"
        assert f"J_stationary: {REASON_BOUNDARY}" in r["notes"]
        assert "J_bound: rho(A) not below 1 - 1e-10 up to rounding" in r["notes"]
