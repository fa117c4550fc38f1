"""Benchmark: the paper preset (``svrobs reproduce``) in process, against its floor.

    .venv/bin/python bench/reproduce.py [--scale full|reduced] [--jobs N] [--out DIR]
                                        [--only E1,E2] [--rng pcg64|sfc64]
                                        [--draws wishart|rollouts]
                                        [--naive] [--naive-reps 2] [--naive-runs 10]

1. Measures this machine's rate of normal random numbers (numpy's
   ``standard_normal`` into a large array, one core, for both generators),
   in this run, before the reproduction starts.
2. Runs ``svrobs_cli.reproduce.reproduce(DIR, scale)`` exactly as ``svrobs
   reproduce`` does (all records written, tables, figures, report) and prints,
   per experiment, the normals it draws (none for one that takes or shares
   another's data), their time at the measured rate (its floor), the CPU
   seconds its units took in the worker processes, and the ratio; then the
   whole run: wall time, CPU of this process and of the workers
   (``resource.getrusage``), and both against the floor on ``--jobs`` cores.
3. With ``--naive``: times a naive baseline that loops in Python over cells,
   repetitions and Monte Carlo runs (one repetition's data at a time, one
   cell's estimate, bounds, Kalman gain by scipy's DARE, gain design row by
   row, exact cost by a 200-step covariance loop, stationary cost and Theorem 3
   by scipy's Lyapunov solver, one ``json.dumps`` per record; Monte Carlo one
   run and one step at a time), MEASURED on a small sub-grid and EXTRAPOLATED
   per cell (per run for the Monte Carlo) to the preset's size.

The machine may be shared: the load average is printed, and CPU times are
given beside wall times (docs/performance.md#reproduce).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sla

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from svrobs_cli.reproduce import reproduce
from svrobs_core import parse_spec
from svrobs_core.observer_stages import truth
from svrobs_core.paper import paper_specs
from svrobs_core.seeding import MC_STREAM, RNGS, rng_for, seed_key
from svrobs_core.wishart_draws import DRAWS


# ---------------------------------------------------------------------------
# the naive baseline (Python loops over cells, repetitions, Monte Carlo runs)
# ---------------------------------------------------------------------------
def _radius(n, m, N, N0, T0, su, sw, g, M, delta):
    Mu, Mw = M ** (2 * T0 - 1) * su**2, M ** (2 * T0 - 2)
    tA = 4 * n * (m * M * su**2 + sw**2) / (N * (n * Mu + Mw * sw**2))
    tB = 4 * m * (n * Mu + (Mw + 1) * sw**2) / (N * su**2)

    def H(t, d):
        q = (t + d * g * M**2) / ((1 + g) * N0)
        return np.sqrt(q) + np.sqrt(2 * q * np.log(1 / delta))

    return H(tA, n), H(tB, m)


def _project_row(v, radius):
    a = np.abs(v)
    if a.sum() <= radius:
        return v
    u = np.sort(a)[::-1]
    cs = np.cumsum(u)
    j = np.arange(1, v.size + 1)
    k = max(1, int(np.max(np.where(u - (cs - radius) / j > 0, j, 0))))
    theta = (cs[k - 1] - radius) / k
    return np.sign(v) * np.maximum(a - theta, 0.0)


def _exact_cost_loop(A, B, At, Bt, L, C, su, sw, sv, T):
    n = A.shape[0]
    Acal = np.block([[A, np.zeros((n, n))], [-(A - At), At - L @ C]])
    Bcal = np.block(
        [
            [su * B, sw * np.eye(n), np.zeros((n, C.shape[0]))],
            [-su * (B - Bt), -sw * np.eye(n), sv * L],
        ]
    )
    Q = Bcal @ Bcal.T
    S = np.zeros_like(Q)
    tot = 0.0
    for _ in range(T):
        S = Acal @ S @ Acal.T + Q
        tot += np.trace(S[n:, n:])
    return tot / T


def _h2(F, G):
    if np.max(np.abs(np.linalg.eigvals(F))) >= 1:
        return np.nan
    return float(np.sqrt(np.trace(sla.solve_discrete_lyapunov(F, G @ G.T))))


def _naive_data(spec, si, wi, N, rep):
    """One repetition's regression data (Z, F) by a step-by-step loop over its
    documented draws (u then w of key (si, wi, N, rep), data "all")."""
    system = spec.systems[si]
    A, B, n, m, T0 = system.A, system.B, system.n, system.m, spec.T0
    g = rng_for(spec.seed, seed_key(si, wi, N, rep))
    u = g.standard_normal((m, T0, N)) * system.sigma_u
    w = g.standard_normal((n, T0, N)) * spec.sigma_w[wi]
    x = np.zeros((n, T0 + 1, N))
    for k in range(T0):
        x[:, k + 1] = A @ x[:, k] + B @ u[:, k] + w[:, k]
    Z = np.concatenate([x[:, 1:T0], u[:, 1:T0]]).reshape(n + m, -1)
    F = x[:, 2:].reshape(n, -1)
    return Z, F


def naive_rep(spec, si, N, rep, truth, mc_runs=0):
    """All cells (estimators, gammas) of one repetition, one cell at a time -> JSON lines."""
    system = spec.systems[si]
    A, B, C = system.A, system.B, system.C
    n, m = system.n, system.m
    su, sv, sw = system.sigma_u, system.sigma_v, spec.sigma_w[0]
    T0, T = spec.T0, spec.horizon
    Z, F = _naive_data(spec, si, 0, N, rep)
    N0 = Z.shape[1]
    K, J_star, norms = truth
    lines, J_of = [], {}
    for gamma in spec.gamma:
        theta = np.linalg.solve(Z @ Z.T + gamma * np.eye(n + m), Z @ F.T).T
        Ah, Bh = theta[:, :n], theta[:, n:]
        H_A, H_B = _radius(n, m, N, N0, T0, su, sw, gamma, spec.M, spec.delta)
        rA, rB = np.sqrt((1 + gamma) * H_A), np.sqrt((1 + gamma) * H_B)
        eps_A = np.sqrt(np.sum((np.abs(gamma * Ah) + rA) ** 2))
        eps_B = np.sqrt(np.sum((np.abs(gamma * Bh) + rB) ** 2))
        c = (1 + gamma) * Ah
        rho_ub = np.max(np.abs(np.linalg.eigvals(np.abs(c) + rA)))
        P = sla.solve_discrete_are(c.T, C.T, sw**2 * np.eye(n), sv**2 * np.eye(C.shape[0]))
        K_hat = c @ P @ C.T @ np.linalg.inv(C @ P @ C.T + sv**2 * np.eye(C.shape[0]))
        c0 = c - K_hat @ C
        rad = 1 - spec.margin - n * rA
        cc = np.array([_project_row(row, max(rad, 0.0)) for row in c0])
        Lg = c - cc
        g_L = np.abs(c - Lg @ C).sum(axis=1).max() + n * rA
        rho_true = np.max(np.abs(np.linalg.eigvals(A - Lg @ C)))
        J = _exact_cost_loop(A, B, Ah, Bh, Lg, C, su, sw, sv, T)
        Fm = Ah - Lg @ C
        J_stat = None
        if max(np.max(np.abs(np.linalg.eigvals(A))), np.max(np.abs(np.linalg.eigvals(Fm)))) < 1:
            Acal = np.block([[A, np.zeros((n, n))], [-(A - Ah), Fm]])
            Bcal = np.block(
                [
                    [su * B, sw * np.eye(n), np.zeros((n, n))],
                    [-su * (B - Bh), -sw * np.eye(n), sv * Lg],
                ]
            )
            J_stat = float(np.trace(sla.solve_discrete_lyapunov(Acal, Bcal @ Bcal.T)[n:, n:]))
        hw, hdk = _h2(Fm, np.eye(n)), _h2(Fm, K - Lg)
        epsL = np.linalg.norm(K - Lg, 2)
        Jb = (
            hdk * sv
            + np.sqrt(2) * max(eps_A, eps_B) * hw * norms.hinf_PhiA_B * su
            + np.sqrt(2) * max(eps_A, epsL) * hw * norms.hinf_PhiA_K * sv
        )
        J_mc = J_se = None
        if mc_runs:
            J_mc, J_se = naive_mc(
                A,
                B,
                Ah,
                Bh,
                Lg,
                C,
                su,
                sw,
                sv,
                T,
                rng_for(spec.seed, seed_key(si, 0, N, rep), MC_STREAM),
                mc_runs,
            )
        J_of[gamma] = J
        rec = {
            "system": system.name,
            "sigma_w": sw,
            "N": N,
            "N0": N0,
            "estimator": "svr",
            "gamma": gamma,
            "rep": rep,
            "seed_key": [si, 0, N, rep],
            "A_hat": Ah.tolist(),
            "B_hat": Bh.tolist(),
            "rmse_A": float(np.sqrt(np.mean((Ah - A) ** 2))),
            "rmse_B": float(np.sqrt(np.mean((Bh - B) ** 2))),
            "H_A": H_A,
            "H_B": H_B,
            "r_A": rA,
            "r_B": rB,
            "eps_A": eps_A,
            "eps_B": eps_B,
            "coverage_A": float(np.mean(np.abs(A - c) <= rA)),
            "coverage_B": float(np.mean(np.abs(B - (1 + gamma) * Bh) <= rB)),
            "rho_upper_bound": float(rho_ub),
            "stable_certified": bool(rho_ub < 1),
            "L": Lg.tolist(),
            "g_L": float(g_L),
            "certified": bool(g_L < 1),
            "rho_true": float(rho_true),
            "K": K.tolist(),
            "J_exact": J,
            "J_stationary": J_stat,
            "J_mc": J_mc,
            "J_mc_se": J_se,
            "J_star": J_star,
            "J_bound": None if np.isnan(Jb) else float(Jb),
            "delta_J": None if np.isnan(Jb) else float(Jb - J),
        }
        lines.append(rec)
    for rec in lines:
        ref = J_of.get(spec.gamma_ref)
        rec["cost_ratio"] = None if ref is None else abs(rec["J_exact"] - ref) / ref
    return [json.dumps(r) for r in lines]


def naive_mc(A, B, At, Bt, L, C, su, sw, sv, T, rng, runs):
    """One run and one step at a time (the documented draws, plant and observer)."""
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    vals = np.empty(runs)
    for r in range(runs):
        x, xt, acc = np.zeros(n), np.zeros(n), 0.0
        for _ in range(T):
            z = rng.standard_normal(m + n + p)
            uu, ww, vv = su * z[:m], sw * z[m : m + n], sv * z[m + n :]
            xt = At @ xt + Bt @ uu + L @ (C @ x + vv - C @ xt)
            x = A @ x + B @ uu + ww
            e = xt - x
            acc += e @ e
        vals[r] = acc / T
    return float(vals.mean()), float(vals.std(ddof=1) / np.sqrt(runs))


def naive_estimate_rep(spec, si, wi, N, rep):
    """E1/E2 cells of one repetition: OLS and SVR per gamma with bounds, one at a time."""
    system = spec.systems[si]
    A = system.A
    n, m, T0 = system.n, system.m, spec.T0
    su, sw = system.sigma_u, spec.sigma_w[wi]
    Z, F = _naive_data(spec, si, wi, N, rep)
    out = []
    for gamma in [0.0] + list(spec.gamma):
        if gamma == 0.0:
            theta = np.linalg.lstsq(Z.T, F.T, rcond=None)[0].T
        else:
            theta = np.linalg.solve(Z @ Z.T + gamma * np.eye(n + m), Z @ F.T).T
        Ah, Bh = theta[:, :n], theta[:, n:]
        H_A, H_B = _radius(n, m, N, Z.shape[1], T0, su, sw, gamma, spec.M, spec.delta)
        rA = np.sqrt((1 + gamma) * H_A)
        c = (1 + gamma) * Ah
        rho = np.max(np.abs(np.linalg.eigvals(np.abs(c) + rA)))
        out.append(
            json.dumps(
                {
                    "A_hat": Ah.tolist(),
                    "B_hat": Bh.tolist(),
                    "H_A": H_A,
                    "H_B": H_B,
                    "rho_upper_bound": float(rho),
                    "coverage_A": float(np.mean(np.abs(A - c) <= rA)),
                }
            )
        )
    return out


def time_naive(scale: str, reps: int, runs: int):
    """Per-cell seconds of the naive pipeline (measured on a sub-grid)."""
    full = {k: parse_spec(v) for k, v in paper_specs(scale).items()}
    e4, e2 = full["E4"], full["E2"]
    # first, middle and last N: their mean is the grid's mean N (the data cost is linear in N)
    Ns = (e4.N[0], e4.N[len(e4.N) // 2], e4.N[-1])
    t0 = time.perf_counter()
    cells = 0
    for si in range(len(e4.systems)):
        K, J_star, norms, _ = truth(e4.systems[si], 1.0, e4.horizon)
        for N in Ns:
            for rep in range(reps):
                cells += len(naive_rep(e4, si, N, rep, (K, J_star, norms)))
    t_e4 = (time.perf_counter() - t0) / cells
    t0 = time.perf_counter()
    cells2 = 0
    for si in range(len(e2.systems)):
        for wi in range(len(e2.sigma_w)):
            for N in Ns:
                for rep in range(reps):
                    cells2 += len(naive_estimate_rep(e2, si, wi, N, rep))
    t_e2 = (time.perf_counter() - t0) / cells2
    s = e4.systems[0]
    K, _, _, _ = truth(s, 1.0, e4.horizon)
    t0 = time.perf_counter()
    naive_mc(
        s.A,
        s.B,
        s.A,
        s.B,
        K,
        s.C,
        s.sigma_u,
        1.0,
        s.sigma_v,
        e4.horizon,
        np.random.default_rng(0),
        runs,
    )
    t_run = (time.perf_counter() - t0) / runs
    return {
        "Ns": Ns,
        "e4_cell": t_e4,
        "e4_cells_measured": cells,
        "e2_cell": t_e2,
        "e2_cells_measured": cells2,
        "mc_run": t_run,
        "mc_runs_measured": runs,
    }


# ---------------------------------------------------------------------------
def normal_rate(rng: str, total: int = 24_000_000, block: int = 2_000_000) -> float:
    """Normals per CPU second of one core (the best of the blocks: the least disturbed)."""
    g = np.random.Generator(RNGS[rng](12345))
    buf = np.empty(block)
    g.standard_normal(out=buf)
    best = float("inf")
    for _ in range(total // block):
        t = time.process_time()
        g.standard_normal(out=buf)
        best = min(best, time.process_time() - t)
    return block / best


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scale", default="full", choices=["full", "reduced"])
    ap.add_argument("--jobs", type=int, default=None, help="worker processes (default: CPUs)")
    ap.add_argument("--out", default=None, help="output folder (default: a temporary one)")
    ap.add_argument("--only", default=None, help="experiments, e.g. E1,E2 (default: all)")
    ap.add_argument("--rng", default=None, choices=sorted(RNGS), help="default: the preset's")
    ap.add_argument("--draws", default=None, choices=DRAWS, help="default: the preset's")
    ap.add_argument("--naive", action="store_true", help="also time the naive baseline")
    ap.add_argument("--naive-reps", type=int, default=2)
    ap.add_argument("--naive-runs", type=int, default=10)
    args = ap.parse_args()

    print(
        f"svrobs reproduce, preset paper-section-6, scale {args.scale}; "
        f"{os.cpu_count()} cpus, load average {os.getloadavg()[0]:.2f} (before)"
    )
    rates = {name: normal_rate(name) for name in sorted(RNGS)}
    print(
        "normal random numbers, one core: "
        + ", ".join(f"{k} {v / 1e6:.1f} M/s" for k, v in rates.items())
    )
    tmp = None
    out = args.out
    if out is None:
        tmp = tempfile.TemporaryDirectory(prefix="svrobs-bench-")
        out = tmp.name
    t0, c0 = time.perf_counter(), time.process_time()
    reproduce(
        out,
        scale=args.scale,
        quiet=True,
        n_jobs=args.jobs,
        only=args.only,
        rng=args.rng,
        draws=args.draws,
    )
    wall = time.perf_counter() - t0
    cpu_parent = time.process_time() - c0
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_children = ch.ru_utime + ch.ru_stime
    prov = json.loads((Path(out) / "provenance.json").read_text())
    size = sum(f.stat().st_size for f in Path(out).rglob("*") if f.is_file())
    if tmp is not None:
        tmp.cleanup()
    specs = {k: parse_spec(v) for k, v in paper_specs(args.scale).items() if k in prov["records"]}
    jobs = prov["n_jobs"]

    print(
        f"\nreproduce(scale={args.scale!r}): {wall:.1f} s wall "
        f"(CPU {cpu_parent:.1f} s in this process + {cpu_children:.1f} s in "
        f"{jobs} worker processes), load average {os.getloadavg()[0]:.2f} (after)"
    )
    print(
        f"\n  {'experiment':<12}{'rng':>6}{'normals':>15}{'floor s':>9}"
        f"{'CPU s':>14}{'ratio':>8}   (worker CPU of its units; group wall s)"
    )
    floor_total = 0.0
    for name in specs:
        k = prov["normals"][name]
        rate = rates[prov["rng"][name]]
        floor = k / rate
        floor_total += floor
        spent = prov["worker_cpu_seconds"][name]
        ratio = f"{spent / floor:7.2f}x" if floor > 0 else "      - "
        how = ""
        if name in prov["derived_from"]:
            how = f"(records of {prov['derived_from'][name]})"
        elif name in prov.get("shares_data_of", {}):
            how = f"(in {prov['shares_data_of'][name]}'s pass)"
        elif name in prov["run_seconds"]:
            how = f"{prov['run_seconds'][name]:.1f}"
        print(f"  {name:<12}{prov['rng'][name]:>6}{k:>15,}{floor:>9.2f}{spent:>14.2f}{ratio} {how}")
    rep_cpu = prov.get("report_cpu_seconds", {})
    print(
        f"  {'report':<12}{'':>6}{0:>15,}{0:>9.2f}{sum(rep_cpu.values()):>14.2f}      -  "
        f"(CPU in this process: {', '.join(f'{k} {v:.1f}' for k, v in rep_cpu.items())}; "
        f"{prov['report_seconds']:.1f} s wall after the last run)"
    )
    cpu = cpu_parent + cpu_children
    print(
        f"  {'total':<12}{'':>6}{sum(prov['normals'].values()):>15,}{floor_total:>9.2f}"
        f"{cpu:>14.2f}{cpu / floor_total:7.2f}x  (CPU of every process / floor)"
    )
    floor_wall = floor_total / jobs
    print(
        f"\n  wall {wall:.1f} s on {jobs} cores; floor {floor_wall:.1f} s "
        f"(the normals at the measured rate, {jobs} cores): {wall / floor_wall:.2f}x"
    )
    written = sum(prov["records"].values())
    print(f"  {written:,} records written ({size / 1e6:.0f} MB)")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"  peak memory (max RSS): {rss:.0f} MB in this process, "
        f"{ch.ru_maxrss / 1024:.0f} MB in the largest worker"
    )
    if not args.naive:
        return
    computed = sum(specs[n].n_cells for n in prov["run_seconds"])
    mc_per_system: dict[str, int] = {}
    for s in specs.values():
        if s.has("cost"):
            k = min(s.reps, s.reps if s.mc_reps is None else s.mc_reps)
            k *= len(s.N) * len(s.sigma_w) * s.cells_per_rep
            for x in s.systems:
                mc_per_system[x.name] = max(mc_per_system.get(x.name, 0), k)
    mc_cells = sum(mc_per_system.values())
    print(
        "\nnaive baseline (Python loops over cells, repetitions and Monte Carlo runs), "
        "MEASURED on a sub-grid:"
    )
    nv = time_naive(args.scale, args.naive_reps, args.naive_runs)
    print(
        f"  E4-type cell (estimate .. cost bound, JSON): {nv['e4_cell'] * 1e3:.2f} ms "
        f"({nv['e4_cells_measured']} cells, N in {nv['Ns']})"
    )
    print(
        f"  E2-type cell (estimate + bounds, JSON):      {nv['e2_cell'] * 1e3:.3f} ms "
        f"({nv['e2_cells_measured']} cells)"
    )
    print(
        f"  Monte Carlo, one run of {specs['E3'].horizon} steps: {nv['mc_run'] * 1e3:.2f} ms "
        f"({nv['mc_runs_measured']} runs)"
    )
    n4 = sum(specs[n].n_cells for n in prov["run_seconds"] if specs[n].has("cost"))
    n2 = computed - n4
    naive = nv["e4_cell"] * n4 + nv["e2_cell"] * n2 + nv["mc_run"] * mc_cells * specs["E3"].mc_runs
    print(
        f"EXTRAPOLATED naive time for the same grid: {n4:,} x {nv['e4_cell'] * 1e3:.2f} ms "
        f"+ {n2:,} x {nv['e2_cell'] * 1e3:.3f} ms + {mc_cells:,} MC cells x "
        f"{specs['E3'].mc_runs} runs x {nv['mc_run'] * 1e3:.2f} ms = {naive:,.0f} s "
        f"({naive / 3600:.1f} h, one core, report not included)"
    )
    run_wall = sum(prov["run_seconds"].values())
    print(
        f"ratio naive / ours: {naive / run_wall:,.0f}x on the runs ({run_wall:.1f} s), "
        f"{naive / wall:,.0f}x on the whole reproduce ({wall:.1f} s)"
    )


if __name__ == "__main__":
    main()
