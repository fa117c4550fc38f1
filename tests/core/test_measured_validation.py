"""Validation on held-out rollouts and the excitation check (docs/measured.md#validation).

Every statistic is recomputed here from its formula with plain loops (the
Ljung-Box statistic of one series in its textbook form); the p-values'
calibration is checked by Monte Carlo on data of the true model.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from svrobs_core import parse_spec
from svrobs_core.measured import (
    MeasuredData,
    Model,
    excitation,
    fit_model,
    validate,
    validation_summary,
)

# Used only here: 2 states, 2 inputs.
A = np.array([[0.6, 0.3], [-0.2, 0.7]])
B = np.array([[1.0, 0.0], [0.4, -0.5]])


def rollouts(seed, count, *, lo=20, hi=60, sigma=0.2, coloured=False):
    rng = np.random.default_rng(seed)
    X, U = [], []
    for _ in range(count):
        T = int(rng.integers(lo, hi))
        u = rng.standard_normal((T, 2))
        if coloured:  # a low-pass input: the cross-correlation test must allow it
            for k in range(1, T):
                u[k] = 0.8 * u[k - 1] + 0.6 * u[k]
        x = np.empty((T + 1, 2))
        x[0] = rng.standard_normal(2)
        for k in range(T):
            x[k + 1] = A @ x[k] + B @ u[k] + sigma * rng.standard_normal(2)
        X.append(x)
        U.append(u)
    return MeasuredData(X=X, U=U)


def hand_statistics(model, data):
    """One-step NRMSE / fit, simulation fit, Ljung-Box and the cross-correlation
    statistic of docs/measured.md#validation, with loops."""
    ny, m = data.n, data.m
    Y, P, eps = [], [], []
    sim_fit, sim_all = [], []
    for x, u in zip(data.X, data.U):
        e_roll = []
        xs = x[0].copy()
        sims = []
        for k in range(u.shape[0]):
            p = model.A @ x[k] + model.B @ u[k]
            Y.append(x[k + 1])
            P.append(p)
            e_roll.append(x[k + 1] - p)
            xs = model.A @ xs + model.B @ u[k]
            sims.append(xs.copy())
        eps.append(np.array(e_roll))
        ys, ss = x[1:], np.array(sims)
        sim_all += list(ss)
        sim_fit.append(
            [
                100 * (1 - math.sqrt(np.sum((ys[:, j] - ss[:, j]) ** 2) / np.sum((ys[:, j] - ys[:, j].mean()) ** 2)))
                for j in range(ny)
            ]
        )  # fmt: skip
    Y, P, sim_all = np.array(Y), np.array(P), np.array(sim_all)
    pooled = [
        100 * (1 - math.sqrt(np.sum((Y[:, j] - sim_all[:, j]) ** 2) / np.sum((Y[:, j] - Y[:, j].mean()) ** 2)))
        for j in range(ny)
    ]  # fmt: skip
    nrmse = [
        math.sqrt(np.sum((Y[:, j] - P[:, j]) ** 2) / np.sum((Y[:, j] - Y[:, j].mean()) ** 2))
        for j in range(ny)
    ]
    n = Y.shape[0]
    h = min(20, max(e.shape[0] for e in eps) // 4)
    Q, R = [], np.zeros((ny, h))
    for j in range(ny):
        mu = sum(e[:, j].sum() for e in eps) / n
        s0 = sum(((e[:, j] - mu) ** 2).sum() for e in eps)
        q = 0.0
        for k in range(1, h + 1):
            num, pairs = 0.0, 0
            for e in eps:
                c = e[:, j] - mu
                for t in range(k, c.shape[0]):
                    num += c[t] * c[t - k]
                    pairs += 1
            q += (num / s0) ** 2 / pairs
            R[j, k - 1] = num / s0
        Q.append(n * (n + 2) * q)
    Uall = np.concatenate(data.U)
    S, RHO = np.zeros((ny, m)), np.zeros((ny, m, h + 1))
    for j in range(ny):
        for l in range(m):
            mu_e = sum(e[:, j].sum() for e in eps) / n
            mu_u = Uall[:, l].mean()
            se = sum(((e[:, j] - mu_e) ** 2).sum() for e in eps)
            su = ((Uall[:, l] - mu_u) ** 2).sum()
            rho = np.zeros(h + 1)
            ru = np.zeros(h + 1)
            pairs = np.zeros(h + 1)
            for k in range(h + 1):
                for e, u in zip(eps, data.U):
                    for t in range(k, e.shape[0]):
                        rho[k] += (e[t, j] - mu_e) * (u[t - k, l] - mu_u)
                        ru[k] += (u[t, l] - mu_u) * (u[t - k, l] - mu_u)
                        pairs[k] += 1
            rho /= math.sqrt(se * su)
            RHO[j, l] = rho
            ru /= su
            Ru = np.array([[ru[abs(a - b)] for b in range(h + 1)] for a in range(h + 1)])
            s = n * rho / np.sqrt(pairs)
            S[j, l] = s @ np.linalg.inv(Ru) @ s
    return dict(
        nrmse=nrmse, sim_fit=np.array(sim_fit), pooled=pooled, h=h, Q=np.array(Q), r=R, S=S,
        rho=RHO, n=n,
    )  # fmt: skip


@pytest.mark.parametrize("coloured", [False, True])
def test_statistics_equal_a_hand_computation(coloured):
    held = rollouts(1, 5, coloured=coloured)
    model = Model(A=A + 0.05, B=B - 0.03)  # a slightly wrong model
    v = validate(model, held)
    ref = hand_statistics(model, held)
    np.testing.assert_allclose(v.one_step_nrmse, ref["nrmse"], rtol=1e-12)
    np.testing.assert_allclose(v.one_step_fit, 100 * (1 - np.array(ref["nrmse"])), rtol=1e-12)
    np.testing.assert_allclose(v.simulation_fit, ref["sim_fit"], rtol=1e-10)
    np.testing.assert_allclose(v.simulation_fit_pooled, ref["pooled"], rtol=1e-10)
    np.testing.assert_allclose(v.autocorrelation, ref["r"], rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(v.cross_correlation, ref["rho"], rtol=1e-10, atol=1e-14)
    assert v.lags == ref["h"]
    np.testing.assert_allclose(v.ljung_box_Q, ref["Q"], rtol=1e-10)
    np.testing.assert_allclose(v.ljung_box_p, chi2.sf(ref["Q"], ref["h"]), rtol=1e-10)
    np.testing.assert_allclose(v.cross_S, ref["S"], rtol=1e-9)
    np.testing.assert_allclose(v.cross_p, chi2.sf(ref["S"], ref["h"] + 1), rtol=1e-8)
    assert v.band == pytest.approx(2.5758293035489004 / math.sqrt(ref["n"]))
    d = v.to_dict()
    assert d["lags"] == ref["h"] and len(d["simulated"]) == 5 and len(d["predicted"][0][0]) == 2


@pytest.mark.parametrize("scale", [0.5, 0.999, 1.2, 1.5])
def test_the_open_loop_simulation_is_the_recursion_step_by_step(scale):
    """The prefix scan of the simulation against x_{k+1} = A x_k + B u_k one step at
    a time, on ragged rollouts (up to 4,000 steps): each state within 1e-12 of the
    largest state before it, and a rollout leaves the double range in both or in
    neither. Where the powers the scan needs overflow (scale 1.5) the recursion
    itself runs: the same steps are non-finite."""
    rng = np.random.default_rng(7)
    A3 = rng.standard_normal((3, 3))
    A3 *= scale / np.abs(np.linalg.eigvals(A3)).max()
    B3 = rng.standard_normal((3, 2))
    lengths = [4000, 1, 2500]
    X = [rng.standard_normal((T + 1, 3)) for T in lengths]
    U = [rng.standard_normal((T, 2)) for T in lengths]
    v = validate(Model(A=A3, B=B3), MeasuredData(X=X, U=U))
    left = []
    for x, u, got in zip(X, U, v.simulated):
        want = np.empty_like(x)
        want[0] = x[0]
        with np.errstate(over="ignore", invalid="ignore"):
            for k in range(len(u)):
                want[k + 1] = want[k] @ A3.T + u[k] @ B3.T
        assert got.shape == want.shape
        assert np.isfinite(got).all() == np.isfinite(want).all()
        if scale == 1.5:
            assert (np.isfinite(got) == np.isfinite(want)).all()
        both = np.isfinite(got).all(axis=1) & np.isfinite(want).all(axis=1)
        top = np.maximum.accumulate(np.abs(want[both]).max(axis=1))[:, None]
        assert (np.abs(got[both] - want[both]) <= 1e-12 * top).all()
        left.append(not np.isfinite(want).all())
    assert left == [scale > 1, False, scale > 1.2]  # 1.2^2500 is about 1e198


def test_one_rollout_is_the_textbook_ljung_box():
    held = rollouts(2, 1, lo=80, hi=81)
    model = Model(A=A, B=B)
    v = validate(model, held)
    x, u = held.X[0], held.U[0]
    e = x[1:] - (x[:-1] @ A.T + u @ B.T)
    n, h = e.shape[0], 20
    for j in range(2):
        c = e[:, j] - e[:, j].mean()
        r = np.array([np.sum(c[k:] * c[:-k]) for k in range(1, h + 1)]) / np.sum(c * c)
        Q = n * (n + 2) * np.sum(r**2 / (n - np.arange(1, h + 1)))
        assert v.ljung_box_Q[j] == pytest.approx(Q, rel=1e-12)
        np.testing.assert_allclose(v.autocorrelation[j], r, rtol=1e-12)


def test_a_held_out_rollout_of_one_transition():
    """One target per channel: NRMSE and fit are undefined (0 / 0 spread), null with a
    note, as the simulation fit; the lag tests have no pair inside a rollout."""
    held = rollouts(5, 1, lo=1, hi=2)
    v = validate(Model(A=A, B=B), held)
    d = v.to_dict()
    assert d["one_step_nrmse"] == d["one_step_fit"] == [None, None]
    assert d["simulation_fit"] == [[None, None]] and d["ljung_box_Q"] == [None, None]
    assert v.notes[:2] == [
        "one-step prediction: left the double range or a constant channel (null)",
        "open-loop simulation: left the double range or a constant channel (null)",
    ]
    assert v.notes[2].startswith("whiteness: no pairs") and v.notes[3].startswith("cross-")


def test_a_channel_whose_residual_is_constant_says_why_its_statistics_are_null():
    """x2 identically 0 (a valid dataset): its residual has no correlation, so Q, S and
    their p-values are null, each with a note naming the channel; x1's are given."""
    rng = np.random.default_rng(0)
    X, U = [], []
    for _ in range(6):
        x, u = np.zeros((31, 2)), rng.normal(size=(30, 1))
        for k in range(30):
            x[k + 1, 0] = 0.5 * x[k, 0] + u[k, 0] + 0.1 * rng.normal()
        X.append(x)
        U.append(u)
    v = validate(Model(A=np.diag([0.5, 0.0]), B=np.array([[1.0], [0.0]])), MeasuredData(X=X, U=U))
    d = v.to_dict()
    assert d["ljung_box_Q"][1] is None and d["cross_S"][1] == [None]
    assert d["ljung_box_Q"][0] is not None and d["cross_S"][0][0] is not None
    assert "whiteness: the residual of x2 is constant: Q and its p-value null" in v.notes
    assert "cross-correlation: the residual of x2 is constant: S and its p-value null" in v.notes
    assert not any("x1" in note for note in v.notes)


def test_p_values_are_calibrated_under_the_true_model():
    """200 held-out sets from the true model: P(p < 0.05) within 3 standard errors of 0.05."""
    ps_lb, ps_x = [], []
    for seed in range(200):
        v = validate(Model(A=A, B=B), rollouts(100 + seed, 4, lo=40, hi=80, coloured=True))
        ps_lb += list(v.ljung_box_p)
        ps_x += list(v.cross_p.ravel())
    for ps in (np.array(ps_lb), np.array(ps_x)):
        share = np.mean(ps < 0.05)
        assert abs(share - 0.05) <= 3 * math.sqrt(0.05 * 0.95 / ps.size)
    # and a wrong model is rejected
    bad = validate(Model(A=A * 0.5, B=B), rollouts(7, 4, lo=40, hi=80))
    assert (bad.ljung_box_p < 1e-6).all()


def test_excitation_check():
    data = rollouts(3, 6)
    ex = excitation(data)
    z = [np.concatenate([x[k], u[k]]) for x, u in zip(data.X, data.U) for k in range(u.shape[0])]
    Z = np.array(z)
    lam = np.linalg.eigvalsh(Z.T @ Z / Z.shape[0])
    np.testing.assert_allclose(ex.eigenvalues, lam, rtol=1e-12)
    assert ex.cond == pytest.approx(lam[-1] / lam[0], rel=1e-12) and ex.notes == []
    assert ex.names == ("x1", "x2", "u1", "u2") and ex.N0 == Z.shape[0]
    one = MeasuredData(X=data.X, U=[np.column_stack([u[:, 0], u[:, 0]]) for u in data.U])
    ex1 = excitation(one)  # u2 = u1: the direction u1 - u2 has no data
    assert "do not excite every direction" in ex1.notes[0]
    np.testing.assert_allclose(
        np.abs(ex1.direction), [0, 0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-7
    )
    weak = MeasuredData(
        X=data.X, U=[np.column_stack([u[:, 0], u[:, 0] + 1e-4 * u[:, 1]]) for u in data.U]
    )
    assert "weakly excited" in excitation(weak).notes[0]


@pytest.mark.parametrize("c", [1e200, 1e-200, 1e150])
def test_excitation_check_at_any_magnitude(c):
    """The data times c: the same condition number and direction (the Gram of c Z would
    overflow or underflow), the eigenvalues c^2 times, or null with a note where that
    is beyond the double range (never 0 or inf: they are positive and finite)."""
    data = rollouts(3, 6)
    base = excitation(data)
    scaled = MeasuredData(X=[x * c for x in data.X], U=[u * c for u in data.U])
    ex = excitation(scaled)
    assert ex.cond == pytest.approx(base.cond, rel=1e-9) and base.notes == []
    np.testing.assert_allclose(np.abs(ex.direction), np.abs(base.direction), rtol=1e-9)
    if c == 1e150:
        np.testing.assert_allclose(ex.eigenvalues, base.eigenvalues * c * c, rtol=1e-9)
        assert ex.notes == []
    else:  # c^2 = 1e400 or 1e-400
        assert np.isnan(ex.eigenvalues).all() and ex.to_dict()["lambda_min"] is None
        assert ex.notes[0].startswith("eigenvalues beyond the double range (null)")
    assert ex.to_dict()["cond"] == pytest.approx(base.cond, rel=1e-9)
    one = MeasuredData(X=scaled.X, U=[np.column_stack([u[:, 0], u[:, 0]]) for u in scaled.U])
    assert "do not excite every direction" in excitation(one).notes[0]


def test_excitation_check_tells_bad_units_from_missing_directions():
    """States of sizes 1e6 and 1e-6: the Gram's condition number is about 1e24, but each
    channel scaled to one size excites every direction: the note says the units, not
    that a direction has no data. Collinear inputs stay "not excited" at any scale."""
    data = rollouts(3, 6)
    D = np.array([1e6, 1e-6])
    scaled = MeasuredData(X=[x * D for x in data.X], U=data.U)
    ex = excitation(scaled)
    assert ex.cond > 1e20 and len(ex.notes) == 1
    assert ex.notes[0].startswith("badly scaled: the regressors' sizes differ by a factor of")
    assert "do not excite" not in ex.notes[0] and "x2" in ex.notes[0]
    base = excitation(data).cond
    Z = np.array(
        [np.concatenate([x[k], u[k]]) for x, u in zip(scaled.X, scaled.U) for k in range(len(u))]
    )
    Ze = Z / np.linalg.norm(Z, axis=0)  # a second way: columns of the sample matrix
    lam = np.linalg.eigvalsh(Ze.T @ Ze)
    assert f"(condition number {lam[-1] / lam[0]:.3g})" in ex.notes[0] and base < 1e8
    one = MeasuredData(X=scaled.X, U=[np.column_stack([u[:, 0], u[:, 0]]) for u in data.U])
    assert "do not excite every direction" in excitation(one).notes[0]


def test_excitation_check_of_zero_data():
    data = rollouts(3, 6)
    zero = MeasuredData(X=[0 * x for x in data.X], U=[0 * u for u in data.U])
    ex = excitation(zero)
    assert ex.cond == math.inf and "lambda_min/lambda_max = 0 " in ex.notes[0]


def test_arx_validation_and_summary():
    rng = np.random.default_rng(4)
    X, U = [], []
    for _ in range(12):
        T = 50
        u = rng.standard_normal((T, 1))
        y = np.zeros((T + 1, 1))
        y[:2] = rng.standard_normal((2, 1))
        for k in range(1, T):
            y[k + 1] = 1.1 * y[k] - 0.4 * y[k - 1] + 0.7 * u[k] - 0.2 * u[k - 1]
            y[k + 1] += 0.1 * rng.standard_normal()
        X.append(y)
        U.append(u)
    data = MeasuredData(X=X, U=U)
    spec = parse_spec(
        {
            "dataset": 1,
            "N": [5, 9],
            "holdout": 3,
            "state": {"lags": {"y": 2, "u": 1}},
            "gamma": [0.1],
        }
    )
    model = fit_model(spec, data, estimator="ols")
    a1, a2, b1, b0 = model.A[0, 0], model.A[0, 1], model.A[0, 2], model.B[0, 0]
    assert abs(a1 - 1.1) < 0.05 and abs(a2 + 0.4) < 0.05 and abs(b0 - 0.7) < 0.05
    held = data.take(range(9, 12))
    v = validate(model, held)
    y, u = held.X[0][:, 0], held.U[0][:, 0]
    want = [a1 * y[k] + a2 * y[k - 1] + b0 * u[k] + b1 * u[k - 1] for k in range(1, 50)]
    np.testing.assert_allclose(v.predicted[0][:, 0], want, rtol=1e-12)
    ys = [y[0], y[1]]  # ARX simulation from the first complete state, measured inputs
    for k in range(1, 50):
        ys.append(a1 * ys[k] + a2 * ys[k - 1] + b0 * u[k] + b1 * u[k - 1])
    np.testing.assert_allclose(v.simulated[0][:, 0], ys[1:], rtol=1e-10)
    assert v.simulation_fit_pooled[0] > 80 and v.ljung_box_p[0] > 1e-3
    summary = validation_summary(spec, data)
    assert [m["estimator"] for m in summary["models"]] == ["ols", "svr"]
    assert summary["N"] == 9 and summary["holdout"] == 3 and summary["excitation"]["N0"] == 9 * 49
    assert summary["excitation"]["names"] == ["x1[k]", "x1[k-1]", "u1[k-1]", "u1"]
    assert summary["models"][0]["validation"]["one_step_fit"] == pytest.approx(
        v.one_step_fit.tolist()
    )
    none = validation_summary(parse_spec({**spec.to_dict(), "holdout": 0}), data)
    assert none["models"][0]["validation"] is None and "holdout = 0" in none["notes"][0]
