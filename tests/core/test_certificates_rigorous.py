"""Radii at any conditioning and certificates that hold exactly (docs/uncertainty.md,
sections "Numerical accuracy of the radii" and "Certificates on the boxes").

Oracles: the box recomputed in 60-digit mpmath from the double data
(tests/core/exact_boxes.py); spectral radii of exact rational matrices in
mpmath; g(L) in exact rational arithmetic (fractions); the true system of a
simulation.
"""

from __future__ import annotations

import math
from fractions import Fraction

import mpmath as mp
import numpy as np
import pytest

from svrobs_core import gains, parse_spec, run_spec
from svrobs_core import uncertainty as unc
from svrobs_core.data_factor import U_EXT
from svrobs_core.linalg import perron_upper_bound
from svrobs_core.rollouts import gram_data
from svrobs_core.seeding import seed_key
from tests.core.exact_boxes import FASTSLOW, PAPER_T900, exact_box

TOL = unc.RADIUS_RTOL


def _data(cond: float, *, d: int, N0: int, rng, scale=1e3):
    """Z (d, N0) with singular values scale * logspace(0, -log10(cond)/2): cond(Z Z^T) = cond."""
    Q1, _ = np.linalg.qr(rng.standard_normal((d, d)))
    Q2, _ = np.linalg.qr(rng.standard_normal((N0, d)))
    sv = scale * np.logspace(0, -math.log10(cond) / 2, d)
    return (Q1 * sv) @ Q2.T


def _rel(R, exact):
    return float(np.max(np.abs(R / exact - 1)))


@pytest.mark.parametrize("cond", [1e4, 1e8, 1e12, 1e14, 1e16, 1e17, 1e18, 1e19, 1e20, 1e28])
def test_radii_from_the_data_agree_with_mpmath_or_are_null(cond):
    """Every radius agrees with mpmath to its own error estimate (<= 1e-6), or is
    null with a reason giving cond; defined at least up to cond 1e20 (extended
    precision where the double factor is not enough), OLS null at 1e28."""
    rng = np.random.default_rng(int(math.log10(cond)))
    n, d, N0 = 2, 3, 60
    for _ in range(3):
        Z = _data(cond, d=d, N0=N0, rng=rng)
        F = rng.standard_normal((n, d)) @ Z + 0.1 * rng.standard_normal((n, N0))
        theta = rng.standard_normal((n, d))
        fac = unc.data_factor(Z, F)
        for lam, shrink in ((0.0, 0.0), (1e-9, 0.0), (1e-3, 0.0), (0.0, 0.05)):
            box = unc.self_normalized_box(
                fac, theta, sigma_w=0.5, delta=0.1, lam=lam, S=2.0, shrink=shrink
            )
            ex = exact_box(Z, theta, sigma_w=0.5, delta=0.1, lam=lam, S=2.0, shrink=shrink)
            R = np.concatenate([box.R_A, box.R_B], axis=-1)
            if np.isfinite(R).all():
                err = _rel(R, ex.R)
                assert err <= float(box.rel_err) <= TOL, (cond, lam, err, box.rel_err)
                assert abs(box.eps_A / ex.eps_A - 1) <= float(box.rel_err)
                assert abs(box.eps_B / ex.eps_B - 1) <= float(box.rel_err)
            else:
                why = str(box.reason[()])
                assert "cond(Z Z^T + g I) = " in why or why == unc.REASON_SINGULAR, why
                if why != unc.REASON_SINGULAR:
                    assert float(box.rel_err) > TOL
            if cond <= 1e20 and U_EXT < 1e-18:  # np.longdouble is wider than double
                assert np.isfinite(R).all(), (cond, lam, box.reason)
            if cond >= 1e28 and lam == 0:
                assert not np.isfinite(R).all()


def test_a_formed_gram_loses_the_radii_where_the_data_keep_them():
    """The check has teeth: at cond 1e17 the radii from the formed Z Z^T are off
    by more than 1e-3 (so a Gram-based implementation fails the test above),
    and its own error estimate says so (null), while the data's radii hold."""
    rng = np.random.default_rng(7)
    Z = _data(1e17, d=3, N0=60, rng=rng)
    theta = rng.standard_normal((2, 3))
    ex = exact_box(Z, theta, sigma_w=1.0, delta=0.1, lam=1e-12, S=1.0)
    G = Z @ Z.T
    plain = unc.self_normalized_box(
        unc.GramFactor(lam=np.maximum(np.linalg.eigvalsh(G), 0), U=np.linalg.eigh(G)[1]),
        theta,
        sigma_w=1.0,
        delta=0.1,
        lam=1e-12,
        S=1.0,
    )
    assert not np.isfinite(plain.R_A).all()  # its estimate: not accurate, null
    lam_g, U_g = np.linalg.eigh(G)
    inv = 1 / (np.maximum(lam_g, 0) + 1e-12)
    diag = np.einsum("jk,jk,k->j", U_g, U_g, inv)
    assert np.max(np.abs(ex.beta * np.sqrt(diag) / ex.R[0] - 1)) > 1e-3
    from_data = unc.self_normalized_box(
        unc.data_factor(Z, theta @ Z), theta, sigma_w=1.0, delta=0.1, lam=1e-12, S=1.0
    )
    R = np.concatenate([from_data.R_A, from_data.R_B], axis=-1)
    assert np.isfinite(R).all() and _rel(R, ex.R) <= 1e-6


@pytest.mark.parametrize(
    "spec_obj", [dict(FASTSLOW, reps=6), dict(PAPER_T900, reps=1)], ids=["fastslow", "paper-T900"]
)
def test_ill_conditioned_specs_give_mpmath_radii_or_nulls_and_no_false_certificate(spec_obj):
    spec = parse_spec(spec_obj)
    system = spec.systems[0]
    records = [r for b in run_spec(spec) for r in b]
    keys = [seed_key(0, 0, 20, r) for r in range(spec.reps)]
    _, _, Z, _ = gram_data(system, spec.sigma_w[0], 20, spec.T0, seed=0, keys=keys, keep_data=True)
    defined = 0
    for r in records:
        assert not r["certified"] or r["rho_true"] < 1
        assert not r["stable_certified"]  # both systems are unstable
        RA = np.array(r["radii_A"], dtype=float)
        if r["radii_A"] is None or not np.isfinite(RA).all():
            assert "cond(Z Z^T + g I) = " in r["notes"]
            assert r["certified"] is None and r["stable_certified"] is None
            continue
        lam = 0.0 if r["estimator"] == "ols" else r["gamma"]
        theta = np.concatenate([np.array(r["A_hat"]), np.array(r["B_hat"])], axis=1)
        sw, delta = r["sigma_w"], spec.delta
        ex = exact_box(Z[r["rep"]], theta, sigma_w=sw, delta=delta, lam=lam, S=spec.S_bound)
        R = np.concatenate([RA, np.array(r["radii_B"])], axis=1)
        assert _rel(R, ex.R) <= TOL
        defined += 1
    if U_EXT < 1e-18:  # with a wider long double every radius is given (cond 1e18-1e19)
        assert defined == len(records)


# ---------------------------------------------------------------------------
# rigorous comparisons
# ---------------------------------------------------------------------------
def _exact_rho(M_fracs) -> mp.mpf:
    with mp.workdps(60):
        A = mp.matrix([[mp.mpf(x.numerator) / x.denominator for x in row] for row in M_fracs])
        return max(abs(e) for e in mp.eig(A, left=False, right=False))


def _fr(x):
    return Fraction(float(x))


def test_collatz_wielandt_bound_is_never_below_the_exact_radius_and_is_tight():
    rng = np.random.default_rng(3)
    for k in (1, 2, 3, 5):
        for _ in range(25):
            A = rng.standard_normal((k, k)) * rng.choice([1e-3, 1.0, 1e3])
            R = np.abs(rng.standard_normal((k, k))) * rng.choice([0.0, 1e-14, 0.1])
            bound = float(unc.rho_upper_bound(A, R))
            exact = [[abs(_fr(a)) + _fr(r) for a, r in zip(ra, rr)] for ra, rr in zip(A, R)]
            rho = _exact_rho(exact)
            assert bound >= rho
            assert bound <= float(rho) * (1 + 1e-12) + 1e-300


def _stochastic(rng, k):
    """Rows of exact dyadic rationals summing to 1 exactly: rho = 1."""
    P = rng.integers(1, 9, size=(k, k)).astype(float)
    return P / P.sum(axis=1, keepdims=True)  # rows sum to 1 up to rounding


def test_a_box_whose_exact_radius_is_one_never_certifies():
    """A = P / (1 + g), R = g |A| (the shrunk-ols box of a zero-noise fit): |A| + R
    equals P exactly in real arithmetic, whose rows sum to 1 (rho = 1), while the
    floating point sum can fall below. Exact rationals decide."""
    rng = np.random.default_rng(11)
    for k in (1, 2, 3):
        for g in (1e-12, 1e-9, 1e-3, 0.3):
            for _ in range(10):
                P = _stochastic(rng, k)
                A = P / (1 + g)
                R = g * np.abs(A)
                bound = float(unc.rho_upper_bound(A, R))
                exact = [[abs(_fr(a)) + _fr(r) for a, r in zip(ra, rr)] for ra, rr in zip(A, R)]
                assert bound >= _exact_rho(exact)
                if bound < 1:
                    assert _exact_rho(exact) < 1
    # the plain floating point computation gets it wrong on this one
    A, R = np.array([[1 / (1 + 1e-12)]]), np.array([[1e-12 / (1 + 1e-12)]])
    assert np.abs(A) + R < 1 and not unc.rho_upper_bound(A, R) < 1


def _exact_g(L, A, gamma, R, C):
    one_g = Fraction(1) + _fr(gamma)
    n, p = L.shape
    rows = []
    for i in range(n):
        s = Fraction(0)
        for j in range(n):
            c = one_g * _fr(A[i, j]) - sum(_fr(L[i, k]) * _fr(C[k, j]) for k in range(p))
            s += abs(c) + _fr(R[i, j])
        rows.append(s)
    return max(rows)


def test_g_of_L_is_never_below_the_exact_value_and_is_tight():
    rng = np.random.default_rng(5)
    for n, p in ((1, 1), (2, 1), (3, 2), (3, 3)):
        for _ in range(30):
            A = rng.standard_normal((n, n))
            C = rng.standard_normal((p, n))
            L = rng.standard_normal((n, p))
            R = np.abs(rng.standard_normal((n, n))) * 1e-3
            gamma = float(rng.choice([0.0, 0.05, 1e-12]))
            g = float(gains.certificate(L, A, gamma, None, C=C, R_A=R))
            exact = _exact_g(L, A, gamma, R, C)
            assert Fraction(g) >= exact
            assert g <= float(exact) * (1 + 1e-13)
            # the scalar radius form
            r = float(R.max())
            gs = float(gains.certificate(L, A, gamma, r, C=C))
            assert Fraction(gs) >= _exact_g(L, A, gamma, np.full((n, n), r), C)


def test_g_of_L_near_one_is_certified_only_when_the_exact_value_is_below_one():
    """n = 1, p = 2: c = a - (l1 c1 + l2 c2) ~ 1 for l2 within a few ulps of its
    solution; two rounded products and a sum put the rounded c below 1 in some
    cases where the exact one is not."""
    found = 0
    rng = np.random.default_rng(2)
    for _ in range(400):
        a, l1 = rng.uniform(-1.0, 1.0), rng.uniform(-3.0, 3.0)
        C = rng.uniform(0.5, 2.0, size=(2, 1))  # p = 2 outputs of n = 1 state
        l0 = (a - 1.0 - l1 * C[0, 0]) / C[1, 0]
        for k in range(-3, 4):
            L = np.array([[l1, l0 + k * np.spacing(l0)]])
            A = np.array([[a]])
            exact = _exact_g(L, A, 0.0, np.zeros((1, 1)), C)
            g = float(gains.certificate(L, A, 0.0, None, C=C, R_A=np.zeros((1, 1))))
            assert Fraction(g) >= exact
            assert not (g < 1 and exact >= 1)
            found += bool(abs(A - L @ C)[0, 0] < 1 and exact >= 1)
    assert found > 5  # the plain rounded value is below 1 while the exact one is not


def test_perron_bound_handles_reducible_and_zero_matrices():
    assert perron_upper_bound(np.zeros((3, 3))) == pytest.approx(0, abs=1e-300)
    M = np.array([[0.9, 1.0], [0.0, 0.5]])
    assert 0.9 <= perron_upper_bound(M) <= 0.9 * (1 + 1e-12)
    M = np.array([[0.5, 0.0], [7.0, 0.9]])
    assert 0.9 <= perron_upper_bound(M) <= 0.9 * (1 + 1e-12)
    assert perron_upper_bound(np.array([[np.nan]])) == np.inf


MARGINAL = {
    "systems": [
        {"name": "integrator", "A": [[1.0]], "B": [[1.0]], "sigma_v": 0.1},
        {"name": "averaging", "A": [[0.5, 0.5], [0.25, 0.75]], "B": [[1.0], [0.0]]},
    ],
    "sigma_w": [0.0, 1e-18],
    "N": [2, 5],
    "T0": 5,
    "reps": 10,
    "estimators": ["ols", "shrunk-ols", "svr"],
    "gamma": [1e-12, 1e-3],
    "bounds_method": "self-normalized",
    "delta": 0.05,
    "stages": ["estimate", "bounds"],
    "seed": 0,
}


def test_zero_noise_boxes_on_marginal_systems_never_certify():
    for b in run_spec(parse_spec(MARGINAL)):
        for r in b:
            assert r["stable_certified"] is not True, r


def test_certificate_radii_need_the_data():
    """From a formed Gram matrix the estimate's rounding margin is not bounded, so the
    certificate radii are NaN (no certificate); from the data's factor they are finite
    and at least the box's radii."""
    rng = np.random.default_rng(11)
    Z = _data(1e3, d=3, N0=60, rng=rng)
    theta = rng.standard_normal((2, 3))
    kw = dict(sigma_w=1.0, delta=0.1, lam=1e-6, S=1.0)
    G = Z @ Z.T
    formed = unc.GramFactor(lam=np.maximum(np.linalg.eigvalsh(G), 0), U=np.linalg.eigh(G)[1])
    box = unc.self_normalized_box(formed, theta, **kw)
    assert np.isfinite(box.R_A).all()  # the box itself is accurate at this cond
    R_A_up, R_B_up = unc.certificate_radii(box, formed, theta, lam=1e-6)
    assert np.isnan(R_A_up).all() and np.isnan(R_B_up).all()
    fac = unc.data_factor(Z, theta @ Z)
    box = unc.self_normalized_box(fac, theta, **kw)
    R_A_up, R_B_up = unc.certificate_radii(box, fac, theta, lam=1e-6)
    assert np.isfinite(R_A_up).all() and (R_A_up >= box.R_A).all() and (R_B_up >= box.R_B).all()


def test_certificates_of_huge_data_are_those_of_the_data_scaled_down():
    """sigma_u = sigma_w / 0.1 = 1e100 (the largest valid level) with lambda0 = 1e200 is
    the unit-scale spec times 1e100: the same radii and certificates. The estimate's
    rounding margin squared the normal-equation residual (~||Z||^2 |theta|) and
    overflowed for data from ~1e77 on: the certificates were null, with the note that
    Z Z^T is singular or too ill-conditioned. The 60-digit box of the huge data agrees."""

    def spec(scale):
        system = {"name": "s", "A": [[0.5, 0.2], [-0.1, 0.4]], "B": [[1.0], [0.5]]}
        return parse_spec(
            {
                "systems": [{**system, "sigma_u": scale}],
                "sigma_w": [0.1 * scale],
                "N": [10],
                "T0": 10,
                "reps": 2,
                "estimators": ["ols"],
                "bounds_method": "self-normalized",
                "lambda0": scale * scale,
                "stages": ["estimate", "bounds", "gain"],
            }
        )

    unit, huge = ([r for b in run_spec(spec(s)) for r in b] for s in (1.0, 1e100))
    big = spec(1e100)
    keys = [seed_key(0, 0, 10, r) for r in range(2)]
    _, _, Z, _ = gram_data(big.systems[0], 1e99, 10, 10, seed=0, keys=keys, keep_data=True)
    for a, b in zip(unit, huge):
        assert a["stable_certified"] is True and a["certified"] is True
        assert b["stable_certified"] is True and b["certified"] is True, b["notes"]
        assert b["r_A"] == pytest.approx(a["r_A"], rel=1e-12)
        assert b["rho_upper_bound"] == pytest.approx(a["rho_upper_bound"], rel=1e-12)
        theta = np.hstack([np.array(b["A_hat"]), np.array(b["B_hat"])])
        ex = exact_box(
            Z[b["rep"]], theta, sigma_w=1e99, delta=big.delta, lam=0.0, S=1.0, lambda0=1e200
        )
        R = np.hstack([np.array(b["radii_A"]), np.array(b["radii_B"])])
        assert _rel(R, ex.R) <= TOL
        exact = [[abs(_fr(x)) + _fr(r) for x, r in zip(xa, ra)] for xa, ra in zip(theta, ex.R)]
        assert b["rho_upper_bound"] >= _exact_rho([row[:2] for row in exact])
