"""Per-record quantities derived from several fields: entry errors and Lemma 2
interval ends (docs/science.md#33-lemma-2-entrywise-intervals), SVR minus OLS on
the same data, and the first N at which the stability certificate holds."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, cast

import numpy as np

from ..array_types import Array, FloatArray
from .columns import Columns, Meta, as_columns, by_N, group_indices, mean_of, select, systems_of


def entry_quantities(
    cols: Columns, meta: Meta, mat: str
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per record: max_ij |ΔX_ij|, and the Lemma 2 interval-end envelope
    max_ij(γX̃_ij) + r_X and min_ij(γX̃_ij) − r_X (γ = 0 for OLS), X = A or B.
    NaN where the estimate, the radius or the true system is unknown."""
    n = cols.n
    err = np.full(n, np.nan)
    hi = np.full(n, np.nan)
    lo = np.full(n, np.nan)
    X = cols.data.get(f"{mat}_hat")
    if X is None or X.ndim != 3 or X.shape[1] == 0:
        return err, lo, hi
    g = np.nan_to_num(cols["gamma"], nan=0.0)
    r = cols[f"r_{mat}"]
    for system in systems_of(cols):
        truth = meta.truth.get(system)
        if truth is None:
            continue
        T = truth[0] if mat == "A" else truth[1]
        m = cols["system"] == system
        if T.shape != X.shape[1:]:
            continue
        Xs = X[m]
        err[m] = np.abs(T - Xs).max(axis=(1, 2))
        centre = g[m, None, None] * Xs
        hi[m] = centre.max(axis=(1, 2)) + r[m]
        lo[m] = centre.min(axis=(1, 2)) - r[m]
    return err, lo, hi


def svr_ols_diff(cols: Columns) -> Array:
    """Per SVR record: max_ij |Ã_svr − Ã_ols| against the OLS estimate of the
    same (system, sigma_w, N, rep), i.e. the same data. NaN elsewhere."""
    if "svr_ols_diff" not in cols.cache:
        cols.cache["svr_ols_diff"] = _svr_ols_diff_calc(cols)
    diff: Array = cols.cache["svr_ols_diff"].copy()
    return diff


def _svr_ols_diff_calc(cols: Columns) -> Array:
    out = np.full(cols.n, np.nan)
    X = cols.data.get("A_hat")
    if X is None or X.ndim != 3 or X.shape[1] == 0:
        return out
    keys = list(
        zip(cols["system"], cols["sigma_w"].tolist(), cols["N"].tolist(), cols["rep"].tolist())
    )
    ols_at = {}
    for i in np.nonzero(cols["estimator"] == "ols")[0]:
        ols_at[keys[i]] = i
    for i in np.nonzero(cols["estimator"] == "svr")[0]:
        j = ols_at.get(keys[i])
        if j is not None:
            out[i] = np.abs(X[i] - X[j]).max()
    return out


def all_inside(cols: Columns) -> Array:
    """Per record: 1 where every entry of A and of B is inside its interval
    (coverage_A = coverage_B = 1), 0 where not, NaN where either is null."""
    a, b = cols["coverage_A"], cols["coverage_B"]
    ok = np.isfinite(a) & np.isfinite(b)
    return np.where(ok, ((a == 1) & (b == 1)).astype(float), np.nan)


def first_stable_certified(
    records: Columns | Iterable[dict[str, Any]], share: float = 0.5
) -> dict[tuple[Any, ...], dict[str, Any]]:
    """(system, sigma_w, estimator, gamma) -> {"N", "N0", "share"} of the first N
    at which stable_certified holds in at least ``share`` of the repetitions,
    or None ("never in the grid"); only groups with stable_certified data."""
    cols = as_columns(records)
    out: dict[tuple[Any, ...], dict[str, Any] | None] = {}
    sc = cols["stable_certified"]
    for key, idx in group_indices(
        cols, ("system", "sigma_w", "estimator", "gamma"), np.isfinite(sc)
    ).items():
        m = np.zeros(cols.n, bool)
        m[idx] = True
        x0, Ns, shares, _ = by_N(cols, m, sc, mean_of)
        hit = np.nonzero(shares >= share)[0]
        out[key] = (
            None
            if hit.size == 0
            else {
                "N": int(Ns[hit[0]]),
                "N0": int(round(x0[hit[0]])),
                "share": float(shares[hit[0]]),
                "N_max": int(Ns.max()),
                "N0_max": int(round(x0.max())),
            }
        )
        if out[key] is None:
            out[key] = {
                "N": None,
                "N0": None,
                "share": None,
                "N_max": int(Ns.max()),
                "N0_max": int(round(x0.max())),
            }
    return cast(dict[tuple[Any, ...], dict[str, Any]], out)  # every None was replaced


def ratio_to_reference(
    cols: Columns, m: Array, mr: Array, values: Array
) -> tuple[FloatArray, FloatArray, FloatArray, Array]:
    """Per N: |mean(values[m]) − mean(values[mr])| / mean(values[mr]) -> (N0, N, r, count)."""
    x, Ns, mean, cnt = by_N(cols, m, values, mean_of)
    _, Nr, mean_r, _ = by_N(cols, mr, values, mean_of)
    ref = dict(zip(Nr.tolist(), mean_r.tolist()))
    r = np.array(
        [
            abs(v - ref[n]) / ref[n] if ref.get(n) else np.nan
            for n, v in zip(Ns.tolist(), mean.tolist())
        ]
    )
    return x, Ns, r, cnt


def cost_ratio_of_means(
    cols: Columns, system: str, gamma: float, gamma_ref: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """r(N) = |mean J_γ − mean J_ref| / mean J_ref with J the exact cost
    (docs/science.md#92-how-the-tables-and-figures-aggregate)."""
    m = select(cols, system=system, estimator="svr", gamma=gamma)
    mr = select(cols, system=system, estimator="svr", gamma=gamma_ref)
    x, Ns, r, _ = ratio_to_reference(cols, m, mr, cols["J_exact"])
    return x, Ns, r
