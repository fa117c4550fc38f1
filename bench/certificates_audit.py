"""Audit: the self-normalized radii against 60-digit mpmath, and the certificates
against the truth, on ill-conditioned and marginal specs (docs/uncertainty.md).

Run: PYTHONPATH=. .venv/bin/python bench/certificates_audit.py [NAME ...] [--reps R]

NAME is one of the built-in specs below (default: all). For every record with
``bounds_method`` "self-normalized" the data of its repetition are simulated
again and the box is recomputed in mpmath (tests/core/exact_boxes.py) around
the record's own estimate; the table gives, per decade of cond(Z Z^T + g I),
the records with radii, the nulls, and the largest relative error of the
radii. Then, over all records: the share whose box holds the true A and B,
and the false certificates (``stable_certified`` true with rho(A) >= 1,
``certified`` true with rho(A - L C) >= 1).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from svrobs_core import estimators as est
from svrobs_core.parsing import parse_spec
from svrobs_core.rollouts import gram_data
from svrobs_core.runner import run_spec
from svrobs_core.seeding import seed_key

sys.path.append(str(Path(__file__).resolve().parents[1]))
from tests.core.exact_boxes import FASTSLOW, PAPER_T900, exact_box  # noqa: E402

INTEGRATOR = {
    "systems": [{"name": "integrator", "A": [[1.0]], "B": [[1.0]], "sigma_v": 0.1}],
    "sigma_w": [0.0, 1e-18],
    "N": [2, 5],
    "T0": 5,
    "reps": 20,
    "estimators": ["ols", "shrunk-ols"],
    "gamma": [1e-12],
    "bounds_method": "self-normalized",
    "delta": 0.05,
    "stages": ["estimate", "bounds"],
    "seed": 0,
}
SPECS = {
    "fastslow": FASTSLOW,  # an unstable fast/slow system: cond(Z Z^T + g I) 6e18-1.4e19
    "paper-unstable-T900": PAPER_T900,  # the paper's unstable system over a long rollout
    "integrator": INTEGRATOR,  # a marginal system (rho(A) = 1) without noise: zero-width boxes
    "integrator-bootstrap": dict(
        INTEGRATOR,
        sigma_w=[0.0],
        estimators=["ols", "svr"],
        bounds_method="bootstrap",
        boot_sigma_w="spec",
        boot_reps=20,
    ),
}


def _records(spec):
    return [r for batch in run_spec(spec) for r in batch]


def _data(spec, cache, si, wi, N, rep):
    key = (si, wi, N)
    if key not in cache:
        reps = range(spec.reps)
        _, _, Z, F = gram_data(
            spec.systems[si],
            spec.sigma_w[wi],
            N,
            spec.T0,
            seed=spec.seed,
            keys=[seed_key(si, wi, N, r) for r in reps],
            data=spec.data,
            x0_std=spec.x0_std,
            keep_data=True,
        )
        cache.clear()
        cache[key] = Z
    return cache[key][rep]


def audit(name: str, spec_obj: dict) -> dict:
    spec = parse_spec(spec_obj)
    records = _records(spec)
    names = [s.name for s in spec.systems]
    by_decade: dict[int, list] = defaultdict(lambda: [0, 0, 0.0])  # defined, null, max err
    cache: dict = {}
    inside = total = false_stable = false_cert = stable = cert = 0
    for r in records:
        si, wi = names.index(r["system"]), spec.sigma_w.index(r["sigma_w"])
        system = spec.systems[si]
        A_hat, B_hat = np.array(r["A_hat"]), np.array(r["B_hat"])
        if r["stable_certified"]:
            stable += 1
            false_stable += max(abs(np.linalg.eigvals(system.A))) >= 1
        if r.get("certified"):
            cert += 1
            false_cert += r["rho_true"] is None or r["rho_true"] >= 1
        RA, RB = (np.array(r[f], dtype=float) for f in ("radii_A", "radii_B"))
        defined = r["radii_A"] is not None and np.isfinite(RA).all() and np.isfinite(RB).all()
        if defined:
            total += 1
            inside += bool(
                np.all(np.abs(A_hat - system.A) <= RA) and np.all(np.abs(B_hat - system.B) <= RB)
            )
        if spec.bounds_method != "self-normalized" or not np.isfinite(A_hat).all():
            continue
        Z = _data(spec, cache, si, wi, r["N"], r["rep"])
        g = r["gamma"]
        lam = 0.0
        if r["estimator"] == "svr":
            lam = float(est.ridge_parameters([g], r["N0"], spec.loss_scale)[0])
        shrink = g if r["estimator"] == "shrunk-ols" else 0.0
        theta = np.concatenate([A_hat, B_hat], axis=1)
        ex = exact_box(
            Z,
            theta,
            sigma_w=r["sigma_w"],
            delta=spec.delta,
            lam=lam,
            S=spec.S_bound,
            lambda0=spec.lambda0,
            shrink=shrink,
        )
        dec = int(math.floor(math.log10(ex.cond))) if ex.cond > 0 else -1
        row = by_decade[dec]
        if not defined:
            row[1] += 1
        else:
            R = np.concatenate([RA, RB], axis=1)
            with np.errstate(invalid="ignore", divide="ignore"):
                rel = np.where(ex.R > 0, np.abs(R / ex.R - 1), np.abs(R - ex.R))
            row[0] += 1
            row[2] = max(row[2], float(np.max(rel)))
    return {
        "name": name,
        "records": len(records),
        "decades": dict(sorted(by_decade.items())),
        "inside": (inside, total),
        "stable": (false_stable, stable),
        "certified": (false_cert, cert),
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("names", nargs="*", default=list(SPECS))
    ap.add_argument("--reps", type=int, default=None, help="override every spec's reps")
    args = ap.parse_args(argv)
    for name in args.names:
        spec = dict(SPECS[name])
        if args.reps:
            spec["reps"] = args.reps
        res = audit(name, spec)
        print(f"## {name}: {res['records']} records")
        if res["decades"]:
            print("| cond decade | radii | null | max rel. error vs mpmath |")
            print("|---|---|---|---|")
            for dec, (ok, null, err) in res["decades"].items():
                print(
                    f"| 1e{dec} | {ok} | {null} | {err:.1e} |"
                    if ok
                    else f"| 1e{dec} | 0 | {null} | - |"
                )
        i, t = res["inside"]
        print(f"box holds the true A, B: {i} of {t}" + (f" ({i / t:.3f})" if t else ""))
        print(f"stable_certified true: {res['stable'][1]}, with rho(A) >= 1: {res['stable'][0]}")
        print(
            f"certified true: {res['certified'][1]}, with rho(A - L C) >= 1: {res['certified'][0]}"
        )
        print()


if __name__ == "__main__":
    main()
