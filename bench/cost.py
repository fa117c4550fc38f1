"""Benchmark of the observer-cost evaluators (docs/science.md#6-observer-cost-j) and Theorem 3.

    .venv/bin/python bench/cost.py [--cells 4000] [--mc-cells 5] [--runs 1000]

On the paper's stable system (n=3, m=1, C=I, horizon 200) with perturbed
cells (A~, B~, L) it times, per cell:

* exact_cost, batched over ``--cells`` cells (binary doubling of the covariance);
* a step-by-step batched covariance recursion of the full 2n augmented system
  (stacked matmul, 200 steps), the obvious vectorised alternative;
* stationary_cost and theorem3_bound, batched;
* mc_cost with ``--runs`` runs vectorised, one cell per call (the way the
  pipeline calls it), on ``--mc-cells`` cells;
* a per-run Python loop baseline (loop over runs and time steps, numpy on
  n-vectors): measured on a few runs of one cell and extrapolated linearly
  to ``--runs`` runs (the extrapolation is printed as such).

Times are wall-clock, best of ``--repeat`` repetitions (CPU time also
shown for the two main evaluators); the machine may be shared, so ratios are
more meaningful than absolute numbers.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import scipy.linalg as sla

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from svrobs_core.cost import exact_cost, stationary_cost
from svrobs_core.cost_bound import theorem3_bound, true_system_norms
from svrobs_core.cost_mc import mc_cost
from svrobs_core.norms import spectral_radius

A = np.array([[0.9, 0.01, 0.0], [0.01, 0.9, 0.01], [0.0, 0.01, 0.9]])
B = np.array([[1.0], [1.5], [2.0]])
C = np.eye(3)
SU, SW, SV, T = 1.0, 1.0, 0.1, 200
NOISE = dict(sigma_u=SU, sigma_w=SW, sigma_v=SV)


def kalman():
    P = sla.solve_discrete_are(A.T, C.T, SW**2 * np.eye(3), SV**2 * np.eye(3))
    return A @ P @ C.T @ np.linalg.inv(C @ P @ C.T + SV**2 * np.eye(3))


CPU = {}


def best_of(fn, repeat):
    """Best wall time of ``repeat`` calls (the best CPU time is kept in CPU[fn])."""
    best, cpu, out = np.inf, np.inf, None
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        best = min(best, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    CPU["last"] = cpu
    return best, out


def stepwise_batched(At, Bt, L):
    """Full 2n augmented covariance, one step at a time, batched matmul."""
    N, n = At.shape[0], 3
    Acal = np.zeros((N, 2 * n, 2 * n))
    Acal[:, :n, :n] = A
    Acal[:, n:, :n] = -(A - At)
    Acal[:, n:, n:] = At - L @ C
    Bcal = np.zeros((N, 2 * n, 1 + n + 3))
    Bcal[:, :n, :1] = SU * B
    Bcal[:, :n, 1 : 1 + n] = SW * np.eye(n)
    Bcal[:, n:, :1] = -SU * (B - Bt)
    Bcal[:, n:, 1 : 1 + n] = -SW * np.eye(n)
    Bcal[:, n:, 1 + n :] = SV * L
    Q = Bcal @ np.swapaxes(Bcal, 1, 2)
    AT = np.swapaxes(Acal, 1, 2)
    S = np.zeros_like(Q)
    tot = np.zeros(N)
    for _ in range(T):
        S = Acal @ S @ AT + Q
        tot += np.trace(S[:, n:, n:], axis1=1, axis2=2)
    return tot / T


def python_loop_mc(At, Bt, L, rng, runs):
    """Per-run, per-step Python loop (the naive Monte Carlo)."""
    vals = np.empty(runs)
    for r in range(runs):
        x = np.zeros(3)
        xt = np.zeros(3)
        acc = 0.0
        for _ in range(T):
            u = SU * rng.standard_normal(1)
            w = SW * rng.standard_normal(3)
            v = SV * rng.standard_normal(3)
            y = C @ x + v
            xt = At @ xt + Bt @ u + L @ (y - C @ xt)
            x = A @ x + B @ u + w
            e = xt - x
            acc += e @ e
        vals[r] = acc / T
    return vals.mean(), vals.std(ddof=1) / np.sqrt(runs)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cells", type=int, default=4000)
    ap.add_argument("--mc-cells", type=int, default=5)
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--loop-runs", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    K = kalman()
    rng = np.random.default_rng(0)
    N = args.cells
    At = A + 0.02 * rng.standard_normal((N, 3, 3))
    Bt = B + 0.05 * rng.standard_normal((N, 3, 1))
    L = K + 0.05 * rng.standard_normal((N, 3, 3))
    eps = np.full(N, 0.1)
    print(
        f"paper stable system, n=3, m=1, C=I, horizon {T}; {N} cells; "
        f"{os.cpu_count()} cpus, load avg {os.getloadavg()[0]:.2f}"
    )

    t_exact, J = best_of(
        lambda: exact_cost(A, B, At, Bt, L=L, C=C, **NOISE, horizon=T),
        args.repeat,
    )
    c_exact = CPU["last"]
    t_step, Js = best_of(lambda: stepwise_batched(At, Bt, L), max(1, args.repeat - 1))
    err = np.abs(J / Js - 1).max()
    t_stat, _ = best_of(
        lambda: stationary_cost(A, B, At, Bt, L=L, C=C, **NOISE),
        args.repeat,
    )
    rho_F = spectral_radius(At - L @ C)
    t_stat2, _ = best_of(
        lambda: stationary_cost(A, B, At, Bt, L=L, C=C, **NOISE, rho_F=rho_F),
        args.repeat,
    )
    t_norms, tn = best_of(lambda: true_system_norms(A, B, C, K), 1)
    t_thm3, _ = best_of(
        lambda: theorem3_bound(At, L, C, K, eps_A=eps, eps_B=eps, sigma_u=SU, sigma_v=SV, norms=tn),
        args.repeat,
    )
    t_thm3b, _ = best_of(
        lambda: theorem3_bound(
            At, L, C, K, eps_A=eps, eps_B=eps, sigma_u=SU, sigma_v=SV, norms=tn, rho_F=rho_F
        ),
        args.repeat,
    )
    t_rho, _ = best_of(lambda: spectral_radius(At - L @ C), args.repeat)

    us = 1e6 / N
    print("\nbatched, per cell:")
    print(
        f"  exact_cost (doubling)            {t_exact * us:9.2f} us   (cpu {c_exact * us:.2f} us)"
    )
    print(
        f"  stepwise 2n recursion (matmul)   {t_step * us:9.2f} us   "
        f"(x{t_step / t_exact:.1f} slower; max rel diff {err:.1e})"
    )
    print(
        f"  stationary_cost                  {t_stat * us:9.2f} us   "
        f"({t_stat2 * us:.2f} us with rho_F given)"
    )
    print(
        f"  theorem3_bound                   {t_thm3 * us:9.2f} us   "
        f"({t_thm3b * us:.2f} us with rho_F given)"
    )
    print(f"  spectral_radius(A~ - L C)        {t_rho * us:9.2f} us")
    print(f"  true_system_norms (once/system)  {t_norms * 1e3:9.2f} ms")

    # Monte Carlo, one cell per call
    M = args.mc_cells
    mc_cost(
        A, B, At[0], Bt[0], L=L[0], C=C, **NOISE, horizon=T, rng=np.random.default_rng(0), runs=10
    )  # warm-up
    t0, c0 = time.perf_counter(), time.process_time()
    mc = [
        mc_cost(
            A,
            B,
            At[i],
            Bt[i],
            L=L[i],
            C=C,
            **NOISE,
            horizon=T,
            rng=np.random.default_rng(i),
            runs=args.runs,
        )
        for i in range(M)
    ]
    t_mc = (time.perf_counter() - t0) / M
    c_mc = (time.process_time() - c0) / M
    t_draw, _ = best_of(
        lambda: np.random.default_rng(0).standard_normal((T, args.runs, 7)), args.repeat
    )
    z = max(abs(mc[i][0] - J[i]) / mc[i][1] for i in range(M))
    R = args.loop_runs
    t0 = time.perf_counter()
    python_loop_mc(At[0], Bt[0], L[0], np.random.default_rng(0), R)
    t_loop_meas = time.perf_counter() - t0
    t_loop = t_loop_meas * args.runs / R
    print(f"\nMonte Carlo, {args.runs} runs x {T} steps, per cell:")
    print(
        f"  mc_cost (runs vectorised)        {t_mc * 1e3:9.2f} ms   "
        f"(cpu {c_mc * 1e3:.2f} ms; max |mean - exact| = {z:.2f} se over {M} cells)"
    )
    print(f"    of which drawing the normals   {t_draw * 1e3:9.2f} ms")
    print(
        f"  per-run Python loop              {t_loop * 1e3:9.2f} ms   "
        f"(EXTRAPOLATED from {R} runs measured in {t_loop_meas * 1e3:.1f} ms)"
    )
    print("\nratios per cell:")
    print(f"  mc_cost / exact_cost             {t_mc / (t_exact / N):9.0f} x")
    print(f"  python loop / mc_cost            {t_loop / t_mc:9.0f} x")
    print(f"  python loop / exact_cost         {t_loop / (t_exact / N):9.0f} x")


if __name__ == "__main__":
    main()
