"""Soundness of the measured-data path at its edges (docs/measured.md#guarantees).

Oracles: exact rational least squares (fractions.Fraction) on the very doubles
of a dataset; 60-digit mpmath for the centre, the radii and g(L) of the exact
box (tests/core/exact_boxes.py for the Gram matrix and the spectral radius);
numpy's eigenvalues; the validation statistics written out with loops
(tests/core/test_measured_validation.py).
"""

from __future__ import annotations

import math
import warnings
from fractions import Fraction

import mpmath as mp
import numpy as np
import pytest

from svrobs_core import estimators, parse_spec, plan_units
from svrobs_core.measured import (
    MeasuredData,
    Model,
    run_measured_unit,
    validate,
    validation_summary,
)
from svrobs_core.measured.noise import REASON_INACCURATE, REASON_RANGE
from svrobs_core.norms import REASON_BOUNDARY, REASON_NONFINITE, hinf_norm
from svrobs_core.radius_bound import radius_upper_bound

from .exact_boxes import DPS, exact_box, exact_rho, exact_sigma_bar, gram
from .test_measured_validation import hand_statistics


def records(obj, X, U):
    spec = parse_spec({"dataset": 1, "reps": 1, **obj})
    data = MeasuredData(X=X, U=U)
    return [r for u in plan_units(spec) for r in run_measured_unit(spec, u, data).records()]


def regressors(X, U):
    """Z (d, N0), F (n, N0) of full-state rollouts, by loops."""
    z = [list(x[k]) + list(u[k]) for x, u in zip(X, U) for k in range(u.shape[0])]
    f = [list(x[k + 1]) for x, u in zip(X, U) for k in range(u.shape[0])]
    return np.array(z).T, np.array(f).T


def exact_ols(Z, F):
    """[A B] of OLS on the doubles Z, F, in Fractions (Gauss-Jordan on Z Z^T)."""
    Zq = [[Fraction(float(v)) for v in row] for row in Z]
    Fq = [[Fraction(float(v)) for v in row] for row in F]
    d = len(Zq)
    G = [[sum(a * b for a, b in zip(Zq[i], Zq[j])) for j in range(d)] for i in range(d)]
    out = []
    for f in Fq:
        M = [G[i][:] + [sum(a * b for a, b in zip(f, Zq[i]))] for i in range(d)]
        for c in range(d):
            p = next(i for i in range(c, d) if M[i][c] != 0)
            M[c], M[p] = M[p], M[c]
            for i in range(d):
                if i != c and M[i][c] != 0:
                    q = M[i][c] / M[c][c]
                    M[i] = [a - q * b for a, b in zip(M[i], M[c])]
        out.append([M[i][d] / M[i][i] for i in range(d)])
    return out


# --------------------------------------------------------------------------
# The certificate radii hold the estimate's rounding (from the data's factor)
# --------------------------------------------------------------------------
def integrator_data(seed, e):
    """Noise-free rollouts of A = [[.5, .5], [.5, .5]] (rho = 1), B = [1; 0] under a
    causal feedback input on the grid 2^-e: every step exact in binary."""
    A, B = np.array([[0.5, 0.5], [0.5, 0.5]]), np.array([[1.0], [0.0]])
    rng = np.random.default_rng(seed)
    X, U = [], []
    for _ in range(3):
        x, u = np.empty((9, 2)), np.zeros((8, 1))
        x[0] = rng.integers(-8, 9, 2)
        for k in range(8):
            u[k, 0] = -(x[k, 0] + x[k, 1]) + rng.integers(-4, 5) * 2.0**-e
            x[k + 1] = A @ x[k] + B @ u[k]
        X.append(x)
        U.append(u)
    return X, U


@pytest.mark.parametrize(("seed", "e"), [(4, 8), (1, 10), (6, 10), (8, 10)])
def test_sigma_zero_box_around_an_integrator_never_certifies(seed, e):
    X, U = integrator_data(seed, e)
    Z, F = regressors(X, U)
    theta = exact_ols(Z, F)
    for z, f in zip(Z.T, F.T):  # every target is exactly [A B] z: sigma_w = 0 is true
        assert [sum(t * Fraction(v) for t, v in zip(row, z)) for row in theta] == list(
            map(Fraction, f)
        )
    A = [row[:2] for row in theta]
    assert (A[0][0] - 1) * (A[1][1] - 1) - A[0][1] * A[1][0] == 0  # 1 is an eigenvalue
    (r,) = records(
        {"N": [3], "sigma_w": 0.0, "stages": ["estimate", "bounds", "gain"], "estimators": ["ols"]},
        X,
        U,
    )
    assert r["radii_A"] == [[0.0, 0.0], [0.0, 0.0]]
    assert r["rho_upper_bound"] is None or r["rho_upper_bound"] >= 1.0
    assert r["stable_certified"] is not True and r["certified"] is not True


def test_radii_of_weakly_excited_data_come_from_the_data():
    """cond(Z Z^T) ~ 5e10: the radii are given and equal the 60-digit box."""
    A, B = np.array([[0.6, 0.2], [0.1, 0.5]]), np.array([[1.0], [0.3]])
    rng = np.random.default_rng(1)
    X, U = [], []
    for _ in range(4):
        x, u = np.empty((31, 2)), np.zeros((30, 1))
        x[0] = rng.standard_normal(2)
        for k in range(30):
            u[k, 0] = -0.5 * x[k, 0] + 1e-6 * rng.standard_normal()
            x[k + 1] = A @ x[k] + B @ u[k] + 0.05 * rng.standard_normal(2)
        X.append(x)
        U.append(u)
    (r,) = records(
        {
            "N": [4],
            "sigma_w": 0.05,
            "delta": 0.05,
            "stages": ["estimate", "bounds"],
            "estimators": ["ols"],
        },
        X,
        U,
    )
    Z, _ = regressors(X, U)
    with mp.workdps(DPS):
        G = gram(Z)
        assert 1e10 < float(mp.cond(G, mp.mnorm)) < 1e13
        Gi = mp.inverse(G)
        lmin = min(mp.eigsy(G)[0])
        logdet = mp.log(mp.det(mp.eye(3) + G))
        beta = mp.mpf(0.05) * mp.sqrt(
            (1 + 1 / lmin) * (logdet + 2 * mp.log(mp.mpf(2) / mp.mpf(0.05)))
        )
        R = [float(beta * mp.sqrt(Gi[j, j])) for j in range(3)]
    assert r["radii_A"] is not None and r["radii_B"] is not None
    got = np.hstack([np.array(r["radii_A"]), np.array(r["radii_B"])])
    np.testing.assert_allclose(got, np.tile(R, (2, 1)), rtol=1e-9)


# --------------------------------------------------------------------------
# sigma_w = "estimate": the bound's own error enters the radii's
# --------------------------------------------------------------------------
def one_step_rollouts(Z, F):
    """Rollouts of one transition each whose regressors and targets are Z, F."""
    n = F.shape[0]
    X = [np.stack([Z[:n, k], F[:, k]]) for k in range(Z.shape[1])]
    U = [Z[n:, k][None, :] for k in range(Z.shape[1])]
    return X, U


def ill_conditioned(cond, N0, seed, noise):
    """Z (3, N0) with lambda_min(Z Z^T) = 1 and cond(Z Z^T) = cond; F = Theta Z + noise."""
    rng = np.random.default_rng(seed)
    Q1, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    Q2, _ = np.linalg.qr(rng.standard_normal((N0, 3)))
    Z = (Q1 * math.sqrt(cond) * np.logspace(0, -math.log10(cond) / 2, 3)) @ Q2.T
    theta = np.array([[0.3, 0.1, 0.5], [0.05, 0.2, -0.4]])
    return Z, theta @ Z + noise * rng.standard_normal((2, N0))


def check_estimated_box(r, Z, F, delta):
    """The record's box with sigma_w = "estimate" against the exact one (the exact
    sigma_bar, the box at delta / 2): given radii within 1e-6 of it, and
    stable_certified true only where the exact |A_hat| + R_A has rho < 1 (it is a
    vertex of the box when A_hat >= 0). -> whether the radii were given."""
    sigma_bar, D = exact_sigma_bar(Z, F, delta=delta)
    R = np.hstack([np.array(r["radii_A"], dtype=float), np.array(r["radii_B"], dtype=float)])
    if not np.isfinite(R).all():
        assert REASON_INACCURATE in r["notes"] or sigma_bar is None, r["notes"]
        assert r["stable_certified"] is None
        return False
    assert sigma_bar is not None, mp.nstr(D, 5)
    centre = np.hstack([np.array(r["A_hat"]), np.array(r["B_hat"])])
    ex = exact_box(Z, centre, sigma_w=sigma_bar, delta=delta / 2, lam=0.0, S=1.0)
    assert np.max(np.abs(R / ex.R - 1)) <= 1e-6
    rho = exact_rho(np.abs(centre[:, :2]) + ex.R[:, :2])
    assert r["rho_upper_bound"] >= rho
    if r["stable_certified"]:
        assert rho < 1
    return True


def test_estimated_sigma_w_with_a_vanishing_denominator_certifies_nothing_false():
    """D = chi2 quantile - n c (l + ...) near 0 (0.002): sigma_bar = sqrt(RSS / D) takes
    D's error times 1 / D. From the formed Gram (cond 1e11) it came out 1.8 % low:
    stable_certified was true (rho_upper_bound 0.993) on a box whose vertex |A_hat| + R_A
    has spectral radius 1.004. Its error estimate nulls it, with a note."""
    Z, F = ill_conditioned(1e11, 200, 2, 1.3914273702909675e-4)
    delta = 1.96464e-06
    _, D = exact_sigma_bar(Z, F, delta=delta)
    assert 0 < D < 0.01
    X, U = one_step_rollouts(Z, F)
    obj = {"N": [200], "delta": delta, "stages": ["estimate", "bounds"], "estimators": ["ols"]}
    (r,) = records(obj, X, U)
    check_estimated_box(r, Z, F, delta)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_estimated_sigma_w_of_ill_conditioned_data_comes_from_the_data(seed):
    """cond(Z Z^T) = 9e11: lambda_min from the
    formed Gram was off by 1e-4, the radii by up to 3.5e-5 and rho_upper_bound below the
    exact value; from the data's factor they agree with the 60-digit box."""
    Z, F = ill_conditioned(9e11, 200, seed, 0.1)
    X, U = one_step_rollouts(Z, F)
    obj = {"N": [200], "delta": 0.1, "stages": ["estimate", "bounds"], "estimators": ["ols"]}
    (r,) = records(obj, X, U)
    assert check_estimated_box(r, Z, F, 0.1)


@pytest.mark.parametrize(("cond", "seed"), [(1e14, 0), (1e14, 1), (1e15, 2)])
def test_estimated_sigma_w_of_data_beyond_a_formed_grams_limit_is_given(cond, seed):
    """cond(Z Z^T) = 1e14-1e15 with lambda_min = 1: well excited (lambda_min equals
    lambda0), and the data's factor knows lambda_min to 1e-8. The bound sigma_bar and
    the box are given and equal the 60-digit ones; a ratio lambda_min / lambda_max
    below 1e-12 said "singular" whatever the data."""
    Z, F = ill_conditioned(cond, 200, seed, 0.1)
    X, U = one_step_rollouts(Z, F)
    obj = {"N": [200], "delta": 0.1, "stages": ["estimate", "bounds"], "estimators": ["ols"]}
    (r,) = records(obj, X, U)
    assert "singular" not in r["notes"]
    assert check_estimated_box(r, Z, F, 0.1)


@pytest.mark.parametrize("scale", [1e160, 1e-160])
def test_well_excited_data_beyond_the_range_of_their_squares_say_so(scale):
    """sigma_min / sigma_max(Z) = 0.135 at any scale, but at 1e160 Z Z^T overflows and at
    1e-160 lambda_min underflows: the nulls say the data are out of range and to
    rescale, not that they lack excitation or that lambda0 is too small, and no
    warning escapes. The estimate is null too: from a subnormal Z Z^T it was 3e-4 off
    the unscaled one, which OLS (scale-equivariant) equals on rescaled data."""
    A, B = np.array([[0.5, 0.1], [0.0, 0.3]]), np.array([[1.0], [0.5]])
    rng = np.random.default_rng(1)
    X, U = [], []
    for _ in range(2):
        x, u = np.zeros((31, 2)), rng.normal(size=(30, 1))
        x[0] = rng.normal(size=2)
        for k in range(30):
            x[k + 1] = A @ x[k] + B @ u[k] + 0.1 * rng.normal(size=2)
        X.append(x)
        U.append(u)
    obj = {"N": [2], "stages": ["estimate", "bounds"], "estimators": ["ols"]}
    (plain,) = records({**obj, "sigma_w": 0.1}, X, U)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        (r,) = records(
            {**obj, "sigma_w": 0.1 * scale}, [x * scale for x in X], [u * scale for u in U]
        )
    assert r["r_A"] is None and f"bounds: {REASON_RANGE}" in r["notes"]
    for wrong in ("excite every direction", "singular", "too small beside"):
        assert wrong not in r["notes"]
    assert np.isnan(np.array(r["A_hat"], dtype=float)).all()
    assert np.isfinite(plain["A_hat"]).all()
    assert f"estimate: certificates withheld: {REASON_RANGE}" in r["notes"]


@pytest.mark.parametrize(
    ("sw", "given"), [(1e-3, True), (1e-8, True), (1e-12, None), (1e-14, None)]
)
def test_estimated_sigma_w_of_nearly_noise_free_data(sw, given):
    """The residual of data with sigma_w / |x| = 1e-12 is rounding noise for 1e-4 of
    its size: the radii were 5.5e-6 (1e-14: 1.4e-4) off the exact box. They are
    given within 1e-6, or null with a note; at ordinary noise levels they are given."""
    A, B = np.array([[0.5, 0.2], [-0.1, 0.4]]), np.array([[1.0], [0.5]])
    rng = np.random.default_rng(1)
    x, u = np.empty((6, 21, 2)), rng.standard_normal((6, 20, 1))  # 6 rollouts at once
    x[:, 0] = rng.standard_normal((6, 2))
    for k in range(20):
        x[:, k + 1] = x[:, k] @ A.T + u[:, k] @ B.T + sw * rng.standard_normal((6, 2))
    X, U = list(x), list(u)
    obj = {"N": [6], "delta": 0.1, "stages": ["estimate", "bounds"], "estimators": ["ols"]}
    (r,) = records(obj, X, U)
    Z, F = regressors(X, U)
    shown = check_estimated_box(r, Z, F, 0.1)
    if given:
        assert shown


# --------------------------------------------------------------------------
# g(L) and certified use the rounded-up radii
# --------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [3, 8, 13, 16, 17])
def test_certified_gain_holds_on_the_exact_box(seed):
    """A weakly excited feedback loop and a margin of 1e-13: g(L) lands within
    1e-13 of 1, where the radii's rounding decides. certified = true must mean
    the exact g(L) of the exact box (exact OLS centre and radii) is below 1."""
    A, B = np.array([[0.9, 0.09], [0.05, 0.9]]), np.array([[1.0], [0.3]])
    sw, delta = 1e-4, 0.01
    rng = np.random.default_rng(seed)
    X, U = [], []
    for _ in range(4):
        x, u = np.empty((31, 2)), np.zeros((30, 1))
        x[0] = rng.standard_normal(2)
        for k in range(30):
            u[k, 0] = -0.3 * x[k, 0] + 1e-3 * rng.standard_normal()
            x[k + 1] = A @ x[k] + B @ u[k] + sw * rng.standard_normal(2)
        X.append(x)
        U.append(u)
    obj = {"N": [4], "sigma_w": sw, "delta": delta, "margin": 1e-13}
    (r,) = records({**obj, "stages": ["estimate", "bounds", "gain"], "estimators": ["ols"]}, X, U)
    assert r["g_L"] is not None
    Z, F = regressors(X, U)
    L = np.array(r["L"])
    with mp.workdps(DPS):
        G = gram(Z)
        FZ = mp.matrix(
            [[mp.fdot([mp.mpf(v) for v in f], [mp.mpf(v) for v in z]) for z in Z] for f in F]
        )
        Gi = mp.inverse(G)
        theta = FZ * Gi
        lmin = min(mp.eigsy(G)[0])
        logdet = mp.log(mp.det(mp.eye(3) + G))
        beta = mp.mpf(sw) * mp.sqrt((1 + 1 / lmin) * (logdet + 2 * mp.log(2 / mp.mpf(delta))))
        g = max(
            sum(abs(theta[i, j] - mp.mpf(L[i, j])) + beta * mp.sqrt(Gi[j, j]) for j in range(2))
            for i in range(2)
        )
        assert r["g_L"] >= g  # the record's g(L) is never below the exact one
        if r["certified"]:
            assert g < 1


# --------------------------------------------------------------------------
# ARX: the known rows have radius 0 in every certificate
# --------------------------------------------------------------------------
def test_arx_known_rows_enter_rho_with_radius_zero():
    rng = np.random.default_rng(0)
    X, U = [], []
    for _ in range(20):
        y, u = np.zeros((61, 1)), rng.standard_normal((60, 1))
        for k in range(60):
            past = 0.3 * y[k - 1] + 0.1 * u[k - 1] if k else 0.0
            y[k + 1] = 0.55 * y[k] + past + 0.5 * u[k] + 0.02 * rng.standard_normal()
        X.append(y)
        U.append(u)
    (r,) = records(
        {
            "N": [20],
            "sigma_w": 0.02,
            "state": {"lags": {"y": 2, "u": 1}},
            "stages": ["estimate", "bounds", "gain"],
            "estimators": ["ols"],
        },
        X,
        U,
    )
    A, R, L = np.array(r["A_hat"]), np.array(r["radii_A"]), np.array(r["L"])
    assert (R[1:] == 0).all() and (R[0] > 0).all()
    rho = float(exact_rho(np.abs(A) + R))  # the known rows at radius 0
    assert rho <= r["rho_upper_bound"] <= rho * (1 + 1e-9)
    assert r["stable_certified"] is (r["rho_upper_bound"] < 1) and rho < 0.97
    C = np.array([[1.0, 0.0, 0.0]])
    g = float(np.max(np.sum(np.abs(A - L @ C) + R, axis=1)))
    assert g <= r["g_L"] <= g * (1 + 1e-9)


# --------------------------------------------------------------------------
# Validation on one-step held-out rollouts
# --------------------------------------------------------------------------
def short_rollouts(rng, lengths):
    return MeasuredData(
        X=[rng.standard_normal((T + 1, 2)) for T in lengths],
        U=[rng.standard_normal((T, 1)) for T in lengths],
    )


@pytest.mark.parametrize("lengths", [[1], [1, 1, 1]])
def test_validation_of_one_step_rollouts_is_null_with_a_note(lengths):
    model = Model(A=np.array([[0.5, 0.1], [0.0, 0.3]]), B=np.array([[1.0], [0.5]]))
    held = short_rollouts(np.random.default_rng(0), lengths)
    v = validate(model, held)
    assert v.lags == 1
    for x in (v.ljung_box_Q, v.ljung_box_p, v.cross_S, v.cross_p, v.autocorrelation):
        assert np.isnan(x).all()
    assert np.isnan(v.cross_correlation[..., 1]).all()  # lag 0 has pairs, lag 1 none
    eps = np.concatenate(
        [x[1:] - x[:-1] @ model.A.T - u @ model.B.T for x, u in zip(held.X, held.U)]
    )
    Y = np.concatenate([x[1:] for x in held.X])
    with np.errstate(divide="ignore"):  # one target: ||y - mean y|| = 0, NRMSE inf
        nrmse = np.linalg.norm(eps, axis=0) / np.linalg.norm(Y - Y.mean(axis=0), axis=0)
    np.testing.assert_allclose(v.one_step_nrmse, nrmse, rtol=1e-12)
    d = v.to_dict()
    assert d["ljung_box_Q"] == [None, None] and d["cross_S"] == [[None], [None]]
    assert any("whiteness: no pairs" in n for n in d["notes"])
    assert any("cross-correlation: no pairs" in n for n in d["notes"])


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the oracle's fit of a one-step rollout
def test_validation_with_some_one_step_rollouts_equals_the_hand_computation():
    model = Model(A=np.array([[0.5, 0.1], [0.0, 0.3]]), B=np.array([[1.0], [0.5]]))
    held = short_rollouts(np.random.default_rng(1), [6, 1, 1, 3])
    v, ref = validate(model, held), hand_statistics(model, held)
    assert v.lags == ref["h"] == 1
    np.testing.assert_allclose(v.ljung_box_Q, ref["Q"], rtol=1e-10)
    np.testing.assert_allclose(v.cross_S, ref["S"], rtol=1e-9)
    assert not any("no pairs" in n for n in v.notes)


def test_validation_summary_of_arx_with_one_transition_per_rollout():
    rng = np.random.default_rng(0)
    X = [rng.standard_normal((6, 1)) for _ in range(3)]
    U = [rng.standard_normal((5, 1)) for _ in range(3)]
    spec = parse_spec(
        {
            "dataset": 1,
            "N": [2],
            "holdout": 1,
            "sigma_w": 0.1,
            "estimators": ["ols"],
            "state": {"lags": {"y": 1, "u": 4}},
        }
    )
    out = validation_summary(spec, MeasuredData(X=X, U=U))
    (m,) = out["models"]
    assert m["validation"]["ljung_box_p"] == [None] and m["validation"]["lags"] == 1


# --------------------------------------------------------------------------
# A frequency response beyond the double range: a null norm, not an exception
# --------------------------------------------------------------------------
def test_hinf_norm_where_the_response_cannot_be_solved_is_null():
    """F = 1e15 [[1, -1], [1, -1]] is nilpotent (rho = 0; given, so the norm is
    attempted), but e^jw I - F is numerically singular at every w: NaN with its
    reason, while a stable diagonal cell in the same batch keeps its norm 1 / (1 - 0.5)
    (at w = 0). Left to decide its stability itself, the norm is null on the boundary:
    a Jordan block of 1e15 moves its computed eigenvalues by about 1e7."""
    F = np.stack([1e15 * np.array([[1.0, -1.0], [1.0, -1.0]]), np.diag([0.5, 0.25])])
    assert np.abs(np.linalg.eigvals(F[0])).max() < 1
    I = np.eye(2)
    value, reason = hinf_norm(F, I, I, rho=np.array([0.0, 0.5]), return_reason=True)
    assert math.isnan(value[0]) and reason[0] == REASON_NONFINITE
    value, reason = hinf_norm(F, I, I, return_reason=True)
    assert math.isnan(value[0]) and reason[0] == REASON_BOUNDARY
    assert value[1] == pytest.approx(2.0, rel=1e-12) and reason[1] is None


def test_cost_stage_on_a_duplicated_channel_at_1e100(monkeypatch):
    """Two identical state channels at magnitude 1e100. The SVR's QR solve is
    rounding there (it gave entries of +-1.9e14 where the exact estimate's, at 400
    digits, are all 0.163): its refinement step is larger than the estimate, which
    is null. Kept (REFINE_STEP_NULL = inf) as an input to the later stages, its
    computed eigenvalues are below 1 but rounding cannot decide its stability (entries
    of 1e14): J_bound is null with that reason, not a norm of an unstable system."""
    rng = np.random.default_rng(2)
    X = []
    for _ in range(3):
        x = np.empty(6)
        x[0] = rng.standard_normal()
        for k in range(5):
            x[k + 1] = 0.5 * x[k] + 0.1 * rng.standard_normal()
        X.append(1e100 * np.c_[x, x])
    U = [np.zeros((5, 0))] * 3
    obj = {
        "N": [3],
        "sigma_w": 1e99,
        "estimators": ["svr"],
        "stages": ["estimate", "bounds", "gain", "cost", "cost_bound"],
    }
    (r,) = records(obj, X, U)
    assert np.isnan(np.array(r["A_hat"], dtype=float)).all()
    assert "estimate: not finite" in r["notes"]
    monkeypatch.setattr(estimators, "REFINE_STEP_NULL", np.inf)
    (r,) = records(obj, X, U)
    A = np.array(r["A_hat"])
    assert np.abs(np.linalg.eigvals(A)).max() < 1  # computed: stable
    assert np.isinf(radius_upper_bound(A)[1]) or radius_upper_bound(A)[1] > 1
    assert r["J_bound"] is None and "not below 1 - 1e-10 up to rounding" in r["notes"]
