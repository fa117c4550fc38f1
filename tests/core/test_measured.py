"""Jobs on measured data (docs/measured.md): the records of svrobs_core.measured.

Oracles: least squares and ridge by numpy's lstsq on regressors built here
with plain loops; the subsamples from numpy's own SeedSequence; the simulated
job of svrobs_core on the same rollouts (records equal to 1e-12 but for the
fields that need the true system); scipy's DARE for K; the covariance
recursion written out for J*; Theorem 3 with scipy's Lyapunov solver and a
dense frequency grid; the sigma_w bound and the box from their formulas.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import scipy.linalg as sla
from scipy.stats import chi2

from svrobs_core import parse_spec, plan_units, run_unit_result
from svrobs_core.measured import MeasuredData, run_measured_unit
from svrobs_core.rollouts import draw_noise, simulate
from svrobs_core.seeding import seed_key

# A system used only here (2 states, 1 input) and its observer model.
SYS = {
    "name": "meas-eq-2x1",
    "A": [[0.72, 0.18], [-0.11, 0.55]],
    "B": [[0.4], [1.1]],
    "C": [[1.0, 0.0], [0.3, 1.0]],
    "sigma_u": 0.8,
    "sigma_v": 0.25,
}
A_TRUE, B_TRUE = np.array(SYS["A"]), np.array(SYS["B"])
TRUTH = ("rmse_A", "rmse_B", "coverage_A", "coverage_B", "rho_true")
TRUTH += ("J_exact", "J_stationary", "J_mc", "J_mc_se", "cost_ratio", "delta_J")
# Computed from the true system in a simulated job, from the estimate on measured data.
ON_ESTIMATE = ("K", "J_star", "J_bound", "J_opt", "J_opt_bound", "sls_status")


def ragged(seed, count, *, m=1, lo=3, hi=25, sigma_w=0.3):
    """Rollouts of the system above with random lengths, initial states and inputs."""
    rng = np.random.default_rng(seed)
    X, U = [], []
    for _ in range(count):
        T = int(rng.integers(lo, hi))
        x = np.empty((T + 1, 2))
        x[0] = rng.standard_normal(2)
        u = rng.standard_normal((T, m))
        for k in range(T):
            x[k + 1] = A_TRUE @ x[k] + B_TRUE[:, :m] @ u[k] + sigma_w * rng.standard_normal(2)
        X.append(x)
        U.append(u)
    return MeasuredData(X=X, U=U)


def regressors(data: MeasuredData, idx):
    """Z (d, N0), F (n, N0) by loops over the rollouts idx and their steps."""
    z, f = [], []
    for i in idx:
        x, u = data.X[i], data.U[i]
        for k in range(u.shape[0]):
            z.append(list(x[k]) + list(u[k]))
            f.append(list(x[k + 1]))
    return np.array(z).T.reshape(-1, len(z)), np.array(f).T


def subsample(seed, N, r, pool):
    """Repetition r's rollouts (docs/measured.md#data-model) with numpy's SeedSequence."""
    if r == 0:
        return np.arange(N)
    g = np.random.Generator(
        np.random.PCG64(np.random.SeedSequence(seed, spawn_key=(0, 0, N, r, 3)))
    )
    return np.sort(g.choice(pool, size=N, replace=False))


def run(spec_obj, data, unit=None):
    spec = parse_spec(spec_obj)
    units = plan_units(spec) if unit is None else [unit]
    results = [run_measured_unit(spec, u, data) for u in units]
    return spec, [r for res in results for r in res.records()], results


@pytest.mark.parametrize("loss_scale", ["sum", "mean"])
def test_estimates_equal_independent_least_squares(loss_scale):
    data = ragged(1, 30)
    obj = {
        "dataset": 1,
        "N": [6, 20],
        "holdout": 4,
        "reps": 3,
        "seed": 11,
        "estimators": ["ols", "svr", "shrunk-ols"],
        "gamma": [0.1, 2.0],
        "loss_scale": loss_scale,
        "sigma_w": 0.3,
    }
    spec, records, _ = run(obj, data)
    assert len(records) == spec.n_cells == 2 * 3 * 5
    for rec in records:
        idx = subsample(11, rec["N"], rec["rep"], pool=26)
        Z, F = regressors(data, idx)
        assert rec["N0"] == Z.shape[1] == sum(data.U[i].shape[0] for i in idx)
        assert rec["seed_key"] == [0, 0, rec["N"], rec["rep"]]
        ols = np.linalg.lstsq(Z.T, F.T, rcond=None)[0].T
        g = rec["gamma"]
        if rec["estimator"] == "ols":
            want = ols
        elif rec["estimator"] == "shrunk-ols":
            want = ols / (1 + g)
        else:
            lam = g if loss_scale == "sum" else g * Z.shape[1]
            aug = np.vstack([Z.T, math.sqrt(lam) * np.eye(3)])
            want = np.linalg.lstsq(aug, np.vstack([F.T, np.zeros((3, 2))]), rcond=None)[0].T
        got = np.hstack([np.array(rec["A_hat"]), np.array(rec["B_hat"])])
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-10)
        assert rec["system"] == "dataset-1" and rec["sigma_w"] == 0.3


def simulated_rollouts(spec, N, T0):
    """The rollouts a simulated job draws for (system 0, sigma_w 0, N, rep 0), with
    the first state dropped: its regression samples k = 1..T0-1 are all of theirs."""
    x0, u, w = draw_noise(
        spec.seed, [seed_key(0, 0, N, 0)], N=N, T0=T0, n=2, m=1, sigma_u=SYS["sigma_u"],
        sigma_w=spec.sigma_w[0], x0_std=spec.x0_std,
    )  # fmt: skip
    x = simulate(A_TRUE, B_TRUE, x0=x0, u=u, w=w)
    return MeasuredData(
        X=[x[0, :, 1:, i].T for i in range(N)], U=[u[0, :, 1:, i].T for i in range(N)]
    )


STAGES = ["estimate", "bounds", "gain", "cost", "cost_bound"]


def test_records_equal_the_simulated_jobs_on_the_same_data():
    common = {
        "N": [25],
        "gamma": [0.05, 0.5],
        "estimators": ["ols", "svr", "shrunk-ols"],
        "reps": 1,
        "seed": 5,
        "bounds_method": "self-normalized",
        "stages": STAGES,
        "horizon": 40,
        "delta": 0.05,
        "margin": 0.02,
    }
    sim_spec = parse_spec(
        {"systems": [SYS], "sigma_w": [0.1], "T0": 9, "x0_std": 0.5, "mc_runs": 10, **common}
    )
    [unit] = plan_units(sim_spec)
    sim = run_unit_result(sim_spec, unit).records()
    data = simulated_rollouts(sim_spec, 25, 9)
    extra = {"sigma_w": 0.1, "C": SYS["C"], "sigma_v": SYS["sigma_v"], "sigma_u": SYS["sigma_u"]}
    _, meas, _ = run({"dataset": 9, **common, **extra}, data)
    assert len(sim) == len(meas) == 5
    compared = set()
    for a, b in zip(sim, meas):
        for f, va in a.items():
            vb = b[f]
            if f in TRUTH:
                assert vb is None
            elif f in ("system", "notes") + ON_ESTIMATE:
                continue
            elif isinstance(va, (float, list)):
                np.testing.assert_allclose(
                    np.array(vb, float), np.array(va, float), rtol=1e-12, atol=1e-12
                )
                compared.add(f)
            else:
                assert va == vb, f
        assert b["notes"].startswith("measured data: no true system")
        assert all(b[f] is not None for f in ("K", "J_star", "L", "g_L"))
    assert compared == set(
        "sigma_w gamma seed_key A_hat B_hat r_A r_B radii_A radii_B eps_A eps_B"
        " rho_upper_bound L g_L".split()
    )
    assert any(r["certified"] for r in meas) and any(r["stable_certified"] for r in meas)


def theorem3(A, B, C, K, L, *, eps_A, eps_B, sigma_u, sigma_v):
    """Theorem 3 (docs/science.md#7-cost-bound-theorem-3) with scipy's Lyapunov solver and a
    dense grid for H-inf."""
    F = A - L @ C

    def h2(G):
        W = sla.solve_discrete_lyapunov(F, G @ G.T)
        return math.sqrt(np.trace(W))

    def hinf(G):
        n, q = G.shape
        Hs = np.vstack([np.eye(n), np.zeros((q, n))])
        Ds = np.vstack([np.zeros((n, q)), np.eye(q)])
        best = 0.0
        for w in np.linspace(0.0, math.pi, 20001):
            T = Hs @ np.linalg.solve(np.exp(1j * w) * np.eye(n) - A, G) + Ds
            best = max(best, np.linalg.norm(T, 2))
        return best

    hw, hdk = h2(np.eye(2)), h2(K - L)
    e1, e2 = max(eps_A, eps_B), max(eps_A, np.linalg.norm(K - L, 2))
    s2 = math.sqrt(2.0)
    return hdk * sigma_v + s2 * e1 * hw * hinf(B) * sigma_u + s2 * e2 * hw * hinf(K) * sigma_v


def test_kalman_gain_cost_and_theorem3_are_the_estimates():
    data = ragged(2, 20)
    obj = {
        "dataset": 2,
        "N": [20],
        "reps": 1,
        "estimators": ["ols"],
        "sigma_w": 0.3,
        "C": SYS["C"],
        "sigma_v": 0.25,
        "stages": STAGES,
        "horizon": 30,
    }
    _, [rec], _ = run(obj, data)
    A, B, C = np.array(rec["A_hat"]), np.array(rec["B_hat"]), np.array(SYS["C"])
    P = sla.solve_discrete_are(A.T, C.T, 0.09 * np.eye(2), 0.0625 * np.eye(2))
    K = A @ P @ C.T @ np.linalg.inv(C @ P @ C.T + 0.0625 * np.eye(2))
    np.testing.assert_allclose(rec["K"], K, rtol=1e-9, atol=1e-12)
    # J* of the estimate: e+ = (A - K C) e + K v - w from e0 = 0, mean trace over k = 1..T
    S, total = np.zeros((2, 2)), 0.0
    for _ in range(30):
        S = (A - K @ C) @ S @ (A - K @ C).T + 0.09 * np.eye(2) + 0.0625 * K @ K.T
        total += np.trace(S)
    assert rec["J_star"] == pytest.approx(total / 30, rel=1e-10)
    su = float(np.sqrt(np.mean(np.concatenate(data.U) ** 2)))  # sigma_u from the inputs
    L = np.array(rec["L"])
    want = theorem3(A, B, C, K, L, eps_A=rec["eps_A"], eps_B=rec["eps_B"], sigma_u=su, sigma_v=0.25)
    assert rec["J_bound"] == pytest.approx(want, rel=1e-6)


def ref_beta_ols(G, sigma, n, delta, lambda0=1.0):
    lam = np.linalg.eigvalsh(G)
    logdet = np.linalg.slogdet(np.eye(G.shape[0]) + G / lambda0)[1]
    return sigma * math.sqrt((1 + lambda0 / lam[0]) * (logdet + 2 * math.log(n / delta)))


def test_estimated_sigma_w_bound_and_its_box():
    data = ragged(3, 40, lo=10, hi=40)
    delta = 0.1
    obj = {"dataset": 3, "N": [40], "reps": 1, "estimators": ["ols"], "delta": delta}
    _, [rec], _ = run(obj, data)
    Z, F = regressors(data, range(40))
    n, N0 = 2, Z.shape[1]
    G = Z @ Z.T
    theta = np.linalg.lstsq(Z.T, F.T, rcond=None)[0].T
    rss = float(np.sum((F - theta @ Z) ** 2))
    lam = np.linalg.eigvalsh(G)
    c = 1 + 1.0 / lam[0]
    logdet = float(np.sum(np.log(1 + lam)))
    D = chi2.ppf(delta / 4, n * N0) - n * c * (logdet + 2 * math.log(n / (delta / 4)))
    sigma_bar = math.sqrt(rss / D)
    sigma_hat = math.sqrt(rss / (n * (N0 - 3)))
    assert 1.0 < sigma_bar / sigma_hat < 1.2
    beta = ref_beta_ols(G, sigma_bar, n, delta / 2)
    R = beta * np.sqrt(np.diag(np.linalg.inv(G)))
    np.testing.assert_allclose(rec["radii_A"], np.tile(R[:2], (2, 1)), rtol=1e-10)
    np.testing.assert_allclose(rec["radii_B"], np.tile(R[2:], (2, 1)), rtol=1e-10)
    assert rec["sigma_w"] == -1.0
    assert f"sigma_hat_w = {sigma_hat:.4g}" in rec["notes"]
    assert f"sigma_bar_w = {sigma_bar:.4g}" in rec["notes"]
    # too few transitions: no bound, so no box, and a note says why
    _, [few], _ = run({**obj, "N": [1]}, ragged(3, 2, lo=3, hi=4))
    assert np.isnan(np.array(few["radii_A"], float)).all() and few["stable_certified"] is None
    assert "too few transitions to bound sigma_w (N0 <= d)" in few["notes"]
    # many transitions, but of data so large that log det(I + G / lambda0) outweighs
    # the chi2 quantile: the denominator is the reason, not N0
    huge = MeasuredData(X=[1e150 * x for x in data.X], U=[1e150 * u for u in data.U])
    _, [big], _ = run(obj, huge)
    assert big["N0"] > 100 and np.isnan(np.array(big["radii_A"], float)).all()
    assert "sigma_w for data of this size: the bound's denominator" in big["notes"]
    assert "(N0 <= d)" not in big["notes"]


def test_a_given_sigma_w_the_data_contradict_is_noted():
    data = ragged(4, 30, sigma_w=1.0)
    _, [rec], _ = run(
        {"dataset": 4, "N": [30], "reps": 1, "estimators": ["ols"], "sigma_w": 0.3}, data
    )
    assert "the data contradict the given sigma_w = 0.3" in rec["notes"]
    _, [ok], _ = run(
        {"dataset": 4, "N": [30], "reps": 1, "estimators": ["ols"], "sigma_w": 1.0}, data
    )
    assert "contradict" not in ok["notes"]


def test_ragged_repetitions_and_any_split_give_the_same_records():
    data = ragged(5, 24)
    obj = {"dataset": 5, "N": [5, 12], "reps": 4, "holdout": 2, "sigma_w": 0.3, "stages": STAGES}
    obj.update(gamma=[0.2], horizon=20)
    spec, whole, results = run(obj, data)
    assert len({r["N0"] for r in whole if r["N"] == 12}) > 1  # N0 differs between repetitions
    for res in results:
        assert res.json_lines() == [json.dumps(r, allow_nan=False) for r in res.records()]
        cols = res.columns()
        np.testing.assert_array_equal(cols["N0"], [r["N0"] for r in res.records()])
    parts = []
    for N in (5, 12):
        for r0, r1 in ((0, 1), (1, 4)):
            unit = {"system": 0, "sigma_w": 0, "N": [N], "reps": [r0, r1]}
            parts += run(obj, data, unit)[1]
    key = lambda r: (r["N"], r["rep"], r["estimator"])  # noqa: E731
    assert sorted(parts, key=key) == sorted(whole, key=key)


def test_no_inputs_runs_every_stage():
    rng = np.random.default_rng(6)
    X = []
    for _ in range(12):
        x = np.empty((16, 2))
        x[0] = rng.standard_normal(2)
        for k in range(15):
            x[k + 1] = A_TRUE @ x[k] + 0.5 * rng.standard_normal(2)
        X.append(x)
    data = MeasuredData(X=X, U=[np.zeros((15, 0))] * 12)
    obj = {"dataset": 6, "N": [10], "holdout": 2, "reps": 2, "sigma_w": "estimate"}
    obj.update(stages=STAGES + ["sls"], horizon=20, sls={"T_fir": 8})
    spec, records, results = run(obj, data)
    for rec in records:
        assert rec["B_hat"] == [[], []] and rec["radii_B"] == [[], []]
        assert rec["r_B"] is None and rec["eps_B"] == 0.0
        assert rec["sls_status"] == "optimal" and rec["J_opt"] > 0 and rec["J_bound"] > 0
        idx = subsample(0, 10, rec["rep"], pool=10)
        Z, F = regressors(data, idx)
        want = np.linalg.lstsq(Z.T, F.T, rcond=None)[0].T
        if rec["estimator"] == "ols":
            np.testing.assert_allclose(rec["A_hat"], want, atol=1e-10)
    assert results[0].json_lines() == [json.dumps(r) for r in records]


def test_data_without_excitation_withhold_certificates():
    data = ragged(7, 20)
    flat = MeasuredData(X=data.X, U=[np.zeros_like(u) for u in data.U])  # an input never moved
    obj = {
        "dataset": 7,
        "N": [20],
        "reps": 1,
        "sigma_w": 0.3,
        "stages": ["estimate", "bounds", "gain"],
    }
    _, [ols, svr], _ = run(obj, flat)
    assert ols["stable_certified"] is None and ols["certified"] is None
    assert "Z Z^T is singular" in ols["notes"] and "certificates withheld" in ols["notes"]
    assert svr["radii_A"] is not None  # ridge keeps a box
