"""bounds_method in the spec, the gain design on a radius matrix and the pipeline
(docs/uncertainty.md).

Oracles: a loop for g(L) with a radius matrix; SLSQP on the design problem;
the scalar design (R_A = r 11^T must give the same gain); the uncertainty
module's boxes recomputed from the same data; numpy's SeedSequence streams."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from svrobs_core import SpecError, parse_spec
from svrobs_core.gains import certificate, design_gain, reuse_gains
from svrobs_core.planning import plan_units
from svrobs_core.rollouts import gram_data
from svrobs_core.runner import run_unit
from svrobs_core.seeding import seed_key
from svrobs_core.uncertainty import rho_upper_bound, self_normalized_box

TOY = {
    "name": "toy-3x2",
    "A": [[0.5, 0.2, 0.0], [-0.1, 0.4, 0.1], [0.0, 0.2, 0.3]],
    "B": [[1.0, 0.0], [0.0, 0.5], [0.3, 0.2]],
    "C": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
    "sigma_u": 1.0,
    "sigma_v": 0.3,
}
BASE = {
    "systems": [{**TOY, "C": None}],
    "sigma_w": [0.2],
    "N": [40, 120],
    "T0": 6,
    "gamma": [0.05, 0.5],
    "estimators": ["ols", "svr", "shrunk-ols"],
    "reps": 3,
    "M": 1.0,
    "delta": 0.05,
}


# ---------------------------------------------------------------------------
# spec
# ---------------------------------------------------------------------------
def test_default_spec_is_unchanged_and_new_methods_round_trip():
    plain = parse_spec(BASE)
    assert plain.bounds_method == "paper"
    assert "bounds_method" not in plain.to_dict() and "S" not in plain.to_dict()
    for extra in (
        {"bounds_method": "self-normalized", "S": 2.0, "lambda0": 0.5},
        {"bounds_method": "bootstrap", "boot_reps": 7, "boot_sigma_w": "spec"},
    ):
        s = parse_spec({**BASE, **extra})
        d = s.to_dict()
        assert {k: d[k] for k in extra} == extra
        assert parse_spec(d).to_dict() == d
    sn = parse_spec({**BASE, "bounds_method": "self-normalized"})
    assert sn.S_bound == pytest.approx(np.sqrt(2) * 1.0) and sn.lambda0 == 1.0
    assert parse_spec({**BASE, "bounds_method": "bootstrap"}).boot_reps == 100


@pytest.mark.parametrize(
    "extra,field",
    [
        ({"bounds_method": "exact"}, "bounds_method"),
        ({"S": 1.0}, "S"),
        ({"bounds_method": "bootstrap", "lambda0": 2.0}, "lambda0"),
        ({"bounds_method": "self-normalized", "boot_reps": 5}, "boot_reps"),
        ({"bounds_method": "self-normalized", "S": 0}, "S"),
        ({"bounds_method": "self-normalized", "lambda0": "1"}, "lambda0"),
        ({"bounds_method": "bootstrap", "boot_reps": 1}, "boot_reps"),
        ({"bounds_method": "bootstrap", "boot_sigma_w": "true"}, "boot_sigma_w"),
    ],
)
def test_bad_bounds_options_name_the_field(extra, field):
    with pytest.raises(SpecError) as e:
        parse_spec({**BASE, **extra})
    assert e.value.field == field


# ---------------------------------------------------------------------------
# gain design with a radius matrix
# ---------------------------------------------------------------------------
def _g_loop(L, A, R, C):
    c = A - L @ C
    n = A.shape[0]
    return max(sum(abs(c[i, j]) + R[i, j] for j in range(n)) for i in range(n))


def test_matrix_certificate_matches_a_loop_and_the_scalar_case():
    rng = np.random.default_rng(1)
    A = rng.uniform(-0.5, 0.5, (6, 3, 3))
    L = rng.uniform(-0.5, 0.5, (6, 3, 2))
    C = rng.standard_normal((2, 3))
    R = rng.uniform(0, 0.1, (6, 3, 3))
    g = certificate(L, A, 0.0, None, C=C, R_A=R)
    for k in range(6):
        assert g[k] == pytest.approx(_g_loop(L[k], A[k], R[k], C), rel=1e-12)
    r = np.full(6, 0.04)
    same = certificate(L, A, 0.0, None, C=C, R_A=np.broadcast_to(r[:, None, None], (6, 3, 3)))
    np.testing.assert_allclose(same, certificate(L, A, 0.0, r, C=C), rtol=1e-13)


@pytest.mark.parametrize("C", [np.eye(3), np.array([[1.0, 0, 0], [0, 1.0, 0]])], ids=["I", "2x3"])
def test_uniform_radius_matrix_gives_the_scalar_design(C):
    rng = np.random.default_rng(2)
    A = rng.uniform(-0.4, 0.6, (4, 3, 3))
    K = rng.uniform(-0.3, 0.3, (4, 3, C.shape[0]))
    r = np.array([0.01, 0.05, 0.2, 0.4])  # the last is infeasible (3 r > 0.99)
    scalar = design_gain(A, 0.0, r, C, K_hat=K, margin=0.01)
    matrix = design_gain(
        A, 0.0, None, C, K_hat=K, margin=0.01, R_A=np.broadcast_to(r[:, None, None], (4, 3, 3))
    )
    np.testing.assert_allclose(matrix.L, scalar.L, atol=1e-6)
    np.testing.assert_allclose(matrix.g_L, scalar.g_L, atol=1e-6)
    assert matrix.feasible.tolist() == scalar.feasible.tolist() == [True, True, True, False]


def test_matrix_design_is_the_optimum_of_the_problem():
    """Closed form (C = I) = cvxpy per-row program = SLSQP on the same problem."""
    rng = np.random.default_rng(3)
    A = np.array([[0.7, 0.3, 0.1], [0.2, 0.5, 0.2], [0.0, 0.4, 0.6]])
    K = np.zeros((3, 3))  # far outside the budget: the constraint binds in every row
    R = rng.uniform(0.0, 0.15, (3, 3))
    closed = design_gain(A, 0.0, None, np.eye(3), K_hat=K, margin=0.01, R_A=R)
    cvx = design_gain(A, 0.0, None, np.eye(3), K_hat=K, margin=0.01, R_A=R, method="cvxpy")
    np.testing.assert_allclose(closed.L, cvx.L, atol=1e-6)
    budget = 0.99 - R.sum(axis=1)
    rows = (np.abs(A - closed.L).sum(axis=1), budget)
    np.testing.assert_allclose(*rows, atol=1e-12)  # every row on its own budget

    def cons(x):
        return budget - np.abs(A - x.reshape(3, 3)).sum(axis=1)

    x0 = A.ravel().copy()
    best = minimize(
        lambda x: np.sum(x**2),
        x0,
        constraints=[{"type": "ineq", "fun": cons}],
        method="SLSQP",
        options={"ftol": 1e-14, "maxiter": 500},
    )
    assert np.sum(closed.L**2) <= best.fun + 1e-7
    assert closed.g_L == pytest.approx(0.99) and closed.certified


def test_matrix_design_infeasible_falls_back_to_min_g():
    A = np.array([[0.5, 0.1], [0.2, 0.4]])
    R = np.array([[0.6, 0.5], [0.1, 0.1]])  # row 0 alone exceeds 1
    for C, method in ((np.eye(2), "closed_form"), (np.array([[1.0, 0.5], [0.0, 1.0]]), "cvxpy")):
        res = design_gain(A, 0.0, None, C, K_hat=np.zeros((2, 2)), R_A=R, method=method)
        assert not res.feasible and not res.certified
        assert res.g_L == pytest.approx(1.1, abs=1e-6)  # c = 0 reaches max_i sum_j R_ij


def test_reuse_with_radius_matrices():
    A = np.array([[[0.5, 0.1], [0.0, 0.4]], [[0.52, 0.1], [0.0, 0.41]]])
    R = np.stack([np.full((2, 2), 0.05), np.full((2, 2), 0.04)])
    L = np.stack([np.zeros((2, 2)), np.eye(2) * 0.1])
    out = reuse_gains(L, A, 0.0, None, C=np.eye(2), R_A=R)
    assert out.reused.tolist() == [False, True]
    assert out.g_L[1] == pytest.approx(_g_loop(L[0], A[1], R[1], np.eye(2)))


# ---------------------------------------------------------------------------
# pipeline
# ---------------------------------------------------------------------------
def _records(spec_obj):
    spec = parse_spec(spec_obj)
    return spec, [r for u in plan_units(spec) for r in run_unit(spec, u)]


def test_paper_records_carry_the_method_and_uniform_radii():
    _, recs = _records({**BASE, "stages": ["estimate", "bounds"]})
    for r in recs:
        assert r["bounds_method"] == "paper"
        assert np.all(np.array(r["radii_A"]) == r["r_A"])
        assert np.all(np.array(r["radii_B"]) == r["r_B"])
    _, est_only = _records({**BASE, "stages": ["estimate"]})
    assert all(r["bounds_method"] is None and r["radii_A"] is None for r in est_only)


@pytest.mark.parametrize("loss_scale", ["sum", "mean"])
def test_self_normalized_records_are_the_box_of_the_data(loss_scale):
    spec_obj = {
        **BASE,
        "loss_scale": loss_scale,
        "systems": [TOY],
        "bounds_method": "self-normalized",
        "stages": ["estimate", "bounds", "gain"],
    }
    spec, recs = _records(spec_obj)
    system = spec.systems[0]
    by = {}
    for r in recs:
        by.setdefault((r["N"], r["rep"]), []).append(r)
    for (N, rep), cells in by.items():
        keys = [seed_key(0, 0, N, rep)]
        G = gram_data(system, 0.2, N, 6, seed=0, keys=keys)[0][0]
        N0 = 5 * N
        for r in cells:
            theta = np.concatenate([r["A_hat"], r["B_hat"]], axis=1)
            lam = 0.0
            if r["estimator"] == "svr":
                lam = r["gamma"] * (N0 if loss_scale == "mean" else 1)
            shrink = r["gamma"] if r["estimator"] == "shrunk-ols" else 0.0
            box = self_normalized_box(
                G, theta, sigma_w=0.2, delta=0.05, lam=lam, S=np.sqrt(2), shrink=shrink
            )
            np.testing.assert_allclose(r["radii_A"], box.R_A, rtol=1e-9)
            np.testing.assert_allclose(r["radii_B"], box.R_B, rtol=1e-9)
            assert r["r_A"] == pytest.approx(box.R_A.max(), rel=1e-9)
            assert r["eps_A"] == pytest.approx(float(box.eps_A), rel=1e-9)
            A_hat = np.array(r["A_hat"])
            rho = float(rho_upper_bound(A_hat, box.R_A))
            assert r["rho_upper_bound"] == pytest.approx(rho, rel=1e-9)
            assert r["stable_certified"] == (rho < 1)
            assert r["H_A"] is None and r["thm1_holds_A"] is None
            assert "belong to the paper's method" in r["notes"]
            # the gain is certified on this box: g(L) with the radius matrix, centre A_hat
            g = certificate(np.array(r["L"]), A_hat, 0.0, None, C=system.C, R_A=box.R_A)
            assert r["g_L"] == pytest.approx(float(g), rel=1e-9)
            assert r["certified"] == (g < 1)
            inside = np.abs(system.A - A_hat) <= box.R_A
            assert r["coverage_A"] == pytest.approx(inside.mean())
    assert any(r["certified"] for r in recs)
    if loss_scale == "sum":
        assert any(r["stable_certified"] for r in recs)


def test_sound_methods_run_every_stage_and_do_not_depend_on_the_split():
    for extra in (
        {"bounds_method": "self-normalized"},
        {"bounds_method": "bootstrap", "boot_reps": 8},
        {"bounds_method": "bootstrap", "boot_reps": 8, "boot_sigma_w": "spec"},
        {"bounds_method": "bootstrap", "boot_reps": 8, "draws": "wishart"},
    ):
        spec_obj = {
            **BASE,
            **extra,
            "N": [40],
            "reps": 2,
            "gamma": [0.1],
            "stages": ["estimate", "bounds", "gain", "cost", "cost_bound"],
            "mc_runs": 20,
            "horizon": 20,
            "gamma_ref": 0.1,
        }
        spec, recs = _records(spec_obj)
        assert all(r["bounds_method"] == extra["bounds_method"] for r in recs)
        assert all(r["J_bound"] is not None and r["eps_A"] is not None for r in recs)
        # one unit per repetition: the same records, bit for bit
        split = [
            r
            for rep in range(2)
            for r in run_unit(spec, {"system": 0, "sigma_w": 0, "N": [40], "reps": [rep, rep + 1]})
        ]
        assert split == recs


def test_bootstrap_reuse_gain_along_N():
    spec_obj = {
        **BASE,
        "bounds_method": "bootstrap",
        "boot_reps": 6,
        "reuse_gain": True,
        "stages": ["estimate", "bounds", "gain"],
    }
    _, recs = _records(spec_obj)
    assert len(recs) == 2 * 3 * 5
    assert all(r["g_L"] is not None for r in recs)
