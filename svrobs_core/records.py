"""The result record (docs/spec.md#record-fields): field names, JSON-safe values, summary."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np

from .array_types import Array

KEY_FIELDS = ("system", "sigma_w", "N", "N0", "estimator", "gamma", "rep", "seed_key")
ESTIMATE_FIELDS = ("A_hat", "B_hat", "rmse_A", "rmse_B")
BOUND_FIELDS = (
    "bounds_method",
    "H_A",
    "H_B",
    "r_A",
    "r_B",
    "radii_A",
    "radii_B",
    "eps_A",
    "eps_B",
    "coverage_A",
    "coverage_B",
    "thm1_holds_A",
    "thm1_holds_B",
    "rho_upper_bound",
    "stable_certified",
)
GAIN_FIELDS = ("L", "g_L", "certified", "rho_true", "K")
COST_FIELDS = (
    "J_exact",
    "J_stationary",
    "J_mc",
    "J_mc_se",
    "J_star",
    "cost_ratio",
    "J_bound",
    "delta_J",
)
SLS_FIELDS = ("J_opt", "J_opt_bound", "sls_status")
# The fields computed per cell by the stages (the rest: keys and notes).
CELL_FIELDS = ESTIMATE_FIELDS + BOUND_FIELDS + GAIN_FIELDS + COST_FIELDS + SLS_FIELDS
RECORD_FIELDS = KEY_FIELDS + CELL_FIELDS + ("notes",)
# Every field whose value is a matrix (a list of rows in JSON): the one definition.
MATRIX_FIELDS = ("A_hat", "B_hat", "radii_A", "radii_B", "L", "K")
BOOL_FIELDS = ("thm1_holds_A", "thm1_holds_B", "stable_certified", "certified")
TEXT_FIELDS = ("system", "estimator", "bounds_method", "sls_status", "notes")
# Scalars a user filters, sorts and averages on: one numeric SQL column each.
NUMERIC_FIELDS = tuple(
    f for f in RECORD_FIELDS if f not in MATRIX_FIELDS + TEXT_FIELDS + ("seed_key",)
)
GROUP_FIELDS = ("system", "sigma_w", "N", "estimator", "gamma")


# The glossary of the record fields (docs/spec.md#glossary): field -> (label, unit,
# description). The label is the short head of a column or an axis, the unit "" when
# the value has none (a name, a flag, a count of its own kind is said in words).
# A matrix's entries share the unit of the matrix: A is dimensionless, B maps input
# to state units, L and K output to state units. Booleans are true/false; their summary mean is the share of cells.
FIELD_GLOSSARY: dict[str, tuple[str, str, str]] = {
    "system": ("system", "", "The system's name: a preset or a system object of the spec"),
    "sigma_w": ("σ_w", "state units", "Process-noise standard deviation σ_w of the cell"),
    "N": ("N", "rollouts", "Number of rollouts of the identification experiment"),
    "N0": ("N0", "samples", "Regression samples: (T0 − 1)·N with data 'all', N with 'final'"),
    "estimator": ("estimator", "", "The estimator: ols, svr or shrunk-ols"),
    "gamma": ("γ", "dimensionless", "The estimator's regularisation γ (OLS has none: —)"),
    "rep": ("rep", "index", "Repetition of the grid point, 0 … reps − 1"),
    "seed_key": ("seed key", "", "[system, σ_w index, N, rep]: the cell's random stream"),
    "A_hat": ("Â", "dimensionless", "The estimate of A (n×n)"),
    "B_hat": ("B̂", "state per input unit", "The estimate of B (n×m)"),
    "rmse_A": ("RMSE Â", "dimensionless", "Root mean square of the entries of Â − A"),
    "rmse_B": ("RMSE B̂", "state per input unit", "Root mean square of the entries of B̂ − B"),
    "bounds_method": (
        "bounds method",
        "",
        "How the radii were computed: paper, self-normalized or bootstrap",
    ),
    "H_A": ("H_A", "dimensionless", "Theorem 1's right-hand side H(θ_A, n): r_A² / (1 + γ)"),
    "H_B": ("H_B", "(state per input unit)²", "Theorem 1's right-hand side H(θ_B, m)"),
    "r_A": (
        "r_A",
        "dimensionless",
        "Radius of every entry of A around its estimate (the largest entry radius)",
    ),
    "r_B": (
        "r_B",
        "state per input unit",
        "Radius of every entry of B around its estimate (the largest entry radius)",
    ),
    "radii_A": ("radii A", "dimensionless", "Per-entry radii of A (n×n)"),
    "radii_B": ("radii B", "state per input unit", "Per-entry radii of B (n×m)"),
    "eps_A": ("ε_A", "dimensionless", "Bound on the spectral norm ‖Â − A‖ (Corollary 1)"),
    "eps_B": ("ε_B", "state per input unit", "Bound on the spectral norm ‖B̂ − B‖"),
    "coverage_A": (
        "coverage A",
        "share (0–1)",
        "Share of the true entries of A inside their intervals",
    ),
    "coverage_B": (
        "coverage B",
        "share (0–1)",
        "Share of the true entries of B inside their intervals",
    ),
    "thm1_holds_A": (
        "Thm 1 holds (A)",
        "true/false",
        "Theorem 1's inequality holds for every row of A",
    ),
    "thm1_holds_B": (
        "Thm 1 holds (B)",
        "true/false",
        "Theorem 1's inequality holds for every row of B",
    ),
    "rho_upper_bound": (
        "ρ upper bound",
        "dimensionless",
        "Upper bound of the spectral radius ρ(A) over the box of A",
    ),
    "stable_certified": (
        "stable certified",
        "true/false",
        "A is certified stable: ρ upper bound < 1",
    ),
    "L": ("L", "state per output unit", "The observer gain used (n×p)"),
    "g_L": ("g(L)", "dimensionless", "Certificate g(L) of the observer gain: certified when < 1"),
    "certified": ("certified", "true/false", "The observer is certified: g(L) < 1"),
    "rho_true": ("ρ(A − LC)", "dimensionless", "Spectral radius of the true error dynamics A − LC"),
    "K": ("K", "state per output unit", "Kalman predictor gain of the true system (n×p)"),
    "J_exact": ("J", "state units²", "Mean squared estimation error over the horizon, exact"),
    "J_stationary": (
        "J stationary",
        "state units²",
        "Stationary mean squared estimation error (Lyapunov)",
    ),
    "J_mc": ("J Monte Carlo", "state units²", "Monte Carlo estimate of J over mc_runs runs"),
    "J_mc_se": ("J Monte Carlo s.e.", "state units²", "Standard error of the Monte Carlo J"),
    "J_star": ("J*", "state units²", "J of the true model's Kalman gain (L = K)"),
    "cost_ratio": ("cost ratio", "dimensionless", "|J_γ − J_ref| / J_ref, reference γ = gamma_ref"),
    "J_bound": ("J bound", "state units²", "Theorem 3's upper bound J_b on J"),
    "delta_J": ("ΔJ", "state units²", "J bound − J: the bound holds where > 0"),
    "J_opt": ("J opt", "state units²", "Optimal value of the FIR SLS program"),
    "J_opt_bound": ("J opt bound", "state units²", "The paper's upper bound on J opt"),
    "sls_status": ("SLS status", "", "Solver status of the SLS program"),
    "notes": ("notes", "", "Why fields of the cell are null, and other remarks"),
}


def json_value(value: Any) -> Any:
    """numpy scalars/arrays -> plain Python; NaN/inf -> None (never NaN in JSON)."""
    if value is None:
        return None
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return v if math.isfinite(v) else None
    if isinstance(value, np.ndarray):
        if value.dtype == bool:
            return value.tolist()
        return [json_value(v) for v in value] if value.ndim == 1 else [json_value(r) for r in value]
    if isinstance(value, (list, tuple)):
        return [json_value(v) for v in value]
    return value


def empty_record() -> dict[str, Any]:
    return {f: None for f in RECORD_FIELDS}


SUMMARY_FIELDS = tuple(f for f in NUMERIC_FIELDS if f not in ("N", "N0", "rep", "sigma_w", "gamma"))


OVERFLOW_NOTE = "out of the double range (above 1.8e308)"


def stat_entry(mean: float, std: float, count: int) -> dict[str, Any]:
    """One field's summary of a group; a mean or std that is not a finite double is
    null, with a note (docs/spec.md#summaries)."""
    entry: dict[str, Any] = {"mean": mean, "std": std, "count": count}
    if math.isfinite(mean) and math.isfinite(std):
        return entry
    bad = [k for k in ("mean", "std") if not math.isfinite(entry[k])]
    for k in bad:
        entry[k] = None
    entry["note"] = f"{' and '.join(bad)} {OVERFLOW_NOTE}"
    return entry


def _scaled_stats(
    x: Array,
    ok: Array,
    starts: Array,
    sizes: Array,
    n: Array,
    mean: Array,
    std: Array,
    over: Array,
) -> tuple[Array, Array]:
    """mean and std of the groups ``over`` (whose plain sums overflowed) computed on
    x / max|x| and scaled back; the other groups keep their plain values."""
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        scale = np.maximum.reduceat(np.where(ok, np.abs(x), 0.0), starts)
        scale = np.where(over & (scale > 0), scale, 1.0)
        y = np.where(ok, x / np.repeat(scale, sizes), 0.0)
        m = np.add.reduceat(y, starts) / n
        dev = np.where(ok, y - np.repeat(m, sizes), 0.0)
        sd = np.sqrt(np.add.reduceat(dev * dev, starts) / n)
        return np.where(over, m * scale, mean), np.where(over, sd * scale, std)


def summarize(records: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean, std (ddof=0) and count of every numeric field per group (GROUP_FIELDS).

    Booleans count as 0/1, nulls are skipped. Returns one dict per group:
    ``{system, sigma_w, N, estimator, gamma, count, stats: {field: {mean, std, count}}}``;
    a mean or std beyond the double range is null and the field's entry has a
    ``note`` (:func:`stat_entry`).
    """
    records = list(records)
    cols = {f: [r.get(f) for r in records] for f in GROUP_FIELDS + SUMMARY_FIELDS}
    return summarize_columns(cols)


def summarize_columns(columns: dict[str, Any]) -> list[dict[str, Any]]:
    """:func:`summarize` of records given as columns ({field: sequence}, one value per
    record, None = null), vectorised over groups and fields: one sort, then one
    ``np.add.reduceat`` over the (field, record) array for the sums and one for the
    squared deviations (each row's sums are those of the row alone, to the bit)."""
    keys = list(zip(*(columns[g] for g in GROUP_FIELDS)))
    if not keys:
        return []
    # the groups in the order they first appear, each record's group by a C-level map
    index = {k: i for i, k in enumerate(dict.fromkeys(keys))}
    gid = np.fromiter(map(index.__getitem__, keys), dtype=np.intp, count=len(keys))
    order = np.argsort(gid, kind="stable")
    sizes = np.bincount(gid, minlength=len(index))
    starts = np.concatenate(([0], np.cumsum(sizes)[:-1]))
    present = [f for f in SUMMARY_FIELDS if columns.get(f) is not None]
    X = np.empty((len(present), len(keys)))
    for i, f in enumerate(present):
        x = np.asarray(columns[f], dtype=float)  # None -> nan, booleans -> 0/1
        if x.shape != (len(keys),):
            raise ValueError(f"summary field {f!r} has {x.size} values for {len(keys)} records")
        X[i] = x
    X = X[:, order]
    ok = ~np.isnan(X)
    n = np.add.reduceat(ok.astype(np.int64), starts, axis=1)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        mean = np.add.reduceat(np.where(ok, X, 0.0), starts, axis=1) / n
        dev = np.where(ok, X - np.repeat(mean, sizes, axis=1), 0.0)
        std = np.sqrt(np.add.reduceat(dev * dev, starts, axis=1) / n)
    over = (n > 0) & ~(np.isfinite(mean) & np.isfinite(std))
    for i in np.flatnonzero(over.any(axis=1)).tolist():
        mean[i], std[i] = _scaled_stats(X[i], ok[i], starts, sizes, n[i], mean[i], std[i], over[i])
    finite = (np.isfinite(mean) & np.isfinite(std)).tolist()
    stats: dict[str, tuple[Any, ...]] = {
        f: row for f, row in zip(present, zip(mean.tolist(), std.tolist(), n.tolist(), finite))
    }
    out = []
    for key in sorted(index, key=lambda k: tuple((v is None, v) for v in k)):
        g = index[key]
        group_stats = {}
        for f in SUMMARY_FIELDS:
            if f not in stats or stats[f][2][g] == 0:
                group_stats[f] = {"mean": None, "std": None, "count": 0}
            else:
                mean, std, n, finite = stats[f]
                group_stats[f] = (
                    {"mean": mean[g], "std": std[g], "count": n[g]}
                    if finite[g]
                    else stat_entry(mean[g], std[g], n[g])
                )
        out.append({**dict(zip(GROUP_FIELDS, key)), "count": int(sizes[g]), "stats": group_stats})
    return out


# Fields the report reads: L, K, the radius matrices (r_A, r_B are their largest
# entries) and seed_key are never needed.
REPORT_FIELDS = tuple(
    f for f in RECORD_FIELDS if f not in ("L", "K", "radii_A", "radii_B", "seed_key")
)
# The matrices among them (records' MATRIX_FIELDS without the gains): A_hat, B_hat.
COLUMN_MATRIX_FIELDS = tuple(f for f in MATRIX_FIELDS if f in REPORT_FIELDS)
SCALAR_FIELDS = tuple(f for f in REPORT_FIELDS if f not in COLUMN_MATRIX_FIELDS + TEXT_FIELDS)
