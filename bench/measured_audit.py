"""Audit: what the bounds of docs/measured.md deliver on simulated measured data.

Run: PYTHONPATH=. .venv/bin/python bench/measured_audit.py [--datasets 1000]

1. Box coverage on the 2-state, 2-input system of tests/core/test_measured_coverage.py
   (20 rollouts of 25 steps per dataset, N0 = 500, sigma_w = 0.3, delta = 0.2), per
   estimator, with the given sigma_w and with "estimate": the share of datasets with
   every entry of [A B] in the box, the mean r_A, the share of certified gains, and
   sigma_bar / sigma_hat.
2. The same for the ARX system of that file (2 outputs, lags y 2, u 1).
3. The fixed-design chi-square bound on sigma_w against the bound of
   docs/measured.md on data with inputs adapted to the past (x+ = u + w,
   u_k = 10 when |x_k - 1| < 1 after a unit input, else 0): coverage at 1 - delta1.
"""

from __future__ import annotations

import math
import sys

import numpy as np
from scipy.stats import chi2

sys.path.insert(0, "tests/core")

import test_measured_coverage as mc  # noqa: E402  (the systems and helpers of the tests)


def box_rows(count: int) -> None:
    mc.D = count
    for sigma_w in (mc.SIGMA, "estimate"):
        datasets, _, _ = mc.state_datasets(11)
        per_est, names = mc.records_of({**mc.SPEC, "sigma_w": sigma_w}, datasets)
        for name, recs in zip(names, per_est):
            cover = mc.inside(recs, mc.THETA2).mean()
            r_A = np.mean([r["r_A"] for r in recs])
            cert = np.mean([r["certified"] is True for r in recs])
            print(f"| state | {name} | {sigma_w} | {cover:.3f} | {r_A:.3f} | {cert:.3f} |")
    datasets = mc.arx_datasets(12)
    obj = {**mc.SPEC, "estimators": ["ols", "svr"], "stages": ["estimate", "bounds"]}
    obj.update(state={"lags": {"y": 2, "u": 1}})
    for sigma_w in (0.2, "estimate"):
        per_est, names = mc.records_of({**obj, "sigma_w": sigma_w}, datasets)
        for name, recs in zip(names, per_est):
            A, B = np.array(recs[0]["A_hat"]), np.array(recs[0]["B_hat"])
            truth = np.vstack([mc.THETA_Y, np.hstack([A[2:], B[2:]])])
            cover = mc.inside(recs, truth).mean()
            r_A = np.mean([r["r_A"] for r in recs])
            print(f"| ARX | {name} | {sigma_w} | {cover:.3f} | {r_A:.3f} | - |")


def sigma_rows(reps: int = 200_000) -> None:
    rng = np.random.default_rng(0)
    for K in (5, 20, 100):
        T = 2 * K
        w = rng.standard_normal((reps, T))
        x = np.zeros((reps, T + 1))
        u = np.zeros((reps, T))
        for k in range(T):
            u[:, k] = 1.0 if k % 2 == 0 else np.where(np.abs(x[:, k] - 1.0) < 1.0, 10.0, 0.0)
            x[:, k + 1] = u[:, k] + w[:, k]
        Z = np.stack([x[:, :-1], u], axis=1)
        F = x[:, 1:]
        G = np.einsum("rit,rjt->rij", Z, Z)
        th = np.linalg.solve(G, np.einsum("rt,rjt->rj", F, Z)[..., None])[..., 0]
        rss = ((F - np.einsum("rj,rjt->rt", th, Z)) ** 2).sum(1)
        lam = np.linalg.eigvalsh(G)
        for d1 in (0.05, 0.01):
            fixed = np.mean(rss / chi2.ppf(d1, T - 2) >= 1.0)
            c, ell = 1 + 1 / lam[:, 0], np.log1p(lam).sum(1)
            D = chi2.ppf(d1 / 2, T) - c * (ell + 2 * math.log(2 / d1))
            ok = D > 0
            ours = np.mean(np.where(ok, rss / np.where(ok, D, 1.0) >= 1.0, True))
            ratio = np.median(np.sqrt((T - 2) / D[ok])) if ok.any() else float("nan")
            se = math.sqrt(d1 * (1 - d1) / reps)
            print(
                f"| {T} | {1 - d1} | {fixed:.4f} ({(fixed - 1 + d1) / se:+.1f} se) | "
                f"{ours:.4f} | {ok.mean():.3f} | {ratio:.2f} |"
            )


if __name__ == "__main__":
    count = int(sys.argv[sys.argv.index("--datasets") + 1]) if "--datasets" in sys.argv else 1000
    print("| state | estimator | sigma_w | all inside | mean r_A | certified |")
    box_rows(count)
    print("\n| N0 | nominal | fixed-design coverage | ours | ours defined | sigma_bar/sigma_hat |")
    sigma_rows()
