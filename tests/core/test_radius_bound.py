"""The spectral radius's rounding bound against mpmath's eigenvalues at 60 digits
(docs/science.md#62-stationary-j_stationary): stability is decided on a bound of
the exact radius, not on the computed one."""

from __future__ import annotations

import mpmath as mp
import numpy as np
import pytest

from svrobs_core import parse_spec, run_spec
from svrobs_core.norms import REASON_BOUNDARY, UNIT_CIRCLE_TOL, spectral_radius, stability_radius
from svrobs_core.radius_bound import radius_upper_bound

# computed rho(A) = 0.99965, exact 1.0000664 (a real eigenvalue in (1, 1.0001))
NON_NORMAL = [
    [-1819.5698633034172, -789.3802570957218, 7230.508850043],
    [2262.2801104806517, -5547.757753789981, 27200.245832178367],
    [13300.499084720374, -5094.756997244127, 7368.967499602106],
]


def exact_radius(F: np.ndarray) -> float:
    with mp.workdps(60):
        ev = mp.eig(mp.matrix(F.tolist()), left=False, right=False)
        return float(max(abs(e) for e in ev))


def non_normal(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    """Q T Q^T: eigenvalues on T's diagonal (|.| up to 1.05), off-diagonal of ``scale``."""
    T = np.triu(rng.standard_normal((n, n)) * scale, 1)
    T[np.diag_indices(n)] = rng.uniform(-1.05, 1.05, n)
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    return Q @ T @ Q.T


def test_the_computed_radius_of_a_non_normal_matrix_is_not_its_radius():
    A = np.array(NON_NORMAL)
    exact = exact_radius(A)
    rho, hi = radius_upper_bound(A)
    assert rho < 1 - 1e-4 < 1 < exact <= hi
    assert stability_radius(A) == 1 - UNIT_CIRCLE_TOL / 2  # the boundary, not stable


@pytest.mark.parametrize("scale", [0.0, 1.0, 30.0, 1e3, 1e5])
@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_the_bound_is_never_below_the_exact_radius(n, scale):
    rng = np.random.default_rng(1000 * n + int(np.log10(scale + 1)))
    F = np.stack([non_normal(rng, n, scale) for _ in range(12)])
    rho, hi = radius_upper_bound(F)
    exact = np.array([exact_radius(f) for f in F])
    assert np.all(exact <= hi)
    assert np.all(np.abs(rho - exact) <= hi - rho + 1e-300)
    if scale <= 1.0:  # normal or mildly not: the enclosure stays near the radius
        assert np.all(hi - rho <= (1e-12 if scale == 0 else 1e-6))


def test_stability_is_decided_as_before_where_rounding_cannot_move_it():
    """For matrices whose bound is below the boundary the decision radius is the
    computed radius, bit for bit."""
    rng = np.random.default_rng(7)
    F = rng.standard_normal((5000, 3, 3)) * 0.4
    rho = spectral_radius(F)
    decided = stability_radius(F)
    ok = radius_upper_bound(F)[1] < 1 - UNIT_CIRCLE_TOL
    assert ok.mean() > 0.5
    assert np.array_equal(decided[ok], rho[ok])
    assert np.array_equal(decided[rho >= 1], rho[rho >= 1])


def test_non_finite_and_empty():
    rho, hi = radius_upper_bound(np.array([[[np.nan, 0.0], [0.0, 0.5]], [[0.5, 0], [0, 0.25]]]))
    assert np.isnan(rho[0]) and np.isnan(hi[0])
    assert rho[1] == 0.5 and 0.5 <= hi[1] < 0.5 + 1e-14
    rho, hi = radius_upper_bound(np.zeros((4, 0, 0)))
    assert rho.shape == hi.shape == (4,)
    rho, hi = radius_upper_bound(np.full((2, 2), 1e300))
    assert rho == 2e300 and hi >= rho


def test_records_of_a_system_whose_stability_rounding_cannot_decide():
    """The true A above (exact radius above 1): no stationary cost and no Theorem 3
    bound, each with the boundary reason, where the computed radius alone gave both."""
    spec = parse_spec(
        {
            "systems": [{"name": "nn", "A": NON_NORMAL, "B": [[1.0], [0.5], [0.2]]}],
            "sigma_w": [1.0],
            "N": [20],
            "reps": 1,
            "estimators": ["ols"],
            "stages": ["estimate", "bounds", "gain", "cost", "cost_bound"],
            "mc_runs": 2,
        }
    )
    (r,) = [r for batch in run_spec(spec) for r in batch]
    assert r["J_stationary"] is None and f"J_stationary: {REASON_BOUNDARY}" in r["notes"]
    assert r["J_bound"] is None and "J_bound: rho(A) not below 1 - 1e-10 up to" in r["notes"]


def test_tiny_and_huge_scalings_keep_the_bound():
    """A power of 2 scales the radius exactly: the bound scales with it (its norms
    are taken on the scaled matrix, so no square underflows)."""
    A = np.array(NON_NORMAL)
    exact = exact_radius(A)
    for k in (-560, -200, 0, 100):
        s = 2.0**k
        rho, hi = radius_upper_bound(A * s)
        assert hi >= exact * s, k


def test_a_defective_matrix_leaves_the_others_of_its_batch_decided():
    """np.linalg.inv fails for a whole batch with one singular eigenvector matrix:
    each of the others keeps its own enclosure."""
    M = np.array([[-14399.00676, 10800.004319999998], [-19199.995680000004, 14400.99576]])
    N = np.array([[1.9999999850988388, -2.0], [0.5, -1.4901161193847656e-08]])
    alone = stability_radius(M)
    assert alone < 1 - UNIT_CIRCLE_TOL  # decided stable by its eigenvectors
    both = stability_radius(np.stack([M, N]))
    assert both[0] == alone
    assert radius_upper_bound(np.stack([M, N]))[1][1] >= exact_radius(N)
