"""The result record (docs/spec.md#record-fields): field names, JSON-safe values, summary."""

from __future__ import annotations

import math

import numpy as np

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


def json_value(value):
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


def empty_record() -> dict:
    return {f: None for f in RECORD_FIELDS}


SUMMARY_FIELDS = tuple(f for f in NUMERIC_FIELDS if f not in ("N", "N0", "rep", "sigma_w", "gamma"))


OVERFLOW_NOTE = "out of the double range (above 1.8e308)"


def stat_entry(mean: float, std: float, count: int) -> dict:
    """One field's summary of a group; a mean or std that is not a finite double is
    null, with a note (docs/spec.md#summaries)."""
    entry = {"mean": mean, "std": std, "count": count}
    bad = [k for k in ("mean", "std") if not math.isfinite(entry[k])]
    if bad:
        for k in bad:
            entry[k] = None
        entry["note"] = f"{' and '.join(bad)} {OVERFLOW_NOTE}"
    return entry


def _scaled_stats(x, ok, starts, sizes, n, mean, std, over):
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


def summarize(records) -> list[dict]:
    """Mean, std (ddof=0) and count of every numeric field per group (GROUP_FIELDS).

    Booleans count as 0/1, nulls are skipped. Returns one dict per group:
    ``{system, sigma_w, N, estimator, gamma, count, stats: {field: {mean, std, count}}}``;
    a mean or std beyond the double range is null and the field's entry has a
    ``note`` (:func:`stat_entry`).
    """
    records = list(records)
    cols = {f: [r.get(f) for r in records] for f in GROUP_FIELDS + SUMMARY_FIELDS}
    return summarize_columns(cols)


def summarize_columns(columns: dict) -> list[dict]:
    """:func:`summarize` of records given as columns ({field: sequence}, one value per
    record, None = null), vectorised over groups: one sort, then per field one
    ``np.add.reduceat`` for the sums and one for the squared deviations."""
    keys = list(zip(*(columns[g] for g in GROUP_FIELDS)))
    if not keys:
        return []
    index: dict[tuple, int] = {}
    gid = np.fromiter(
        (index.setdefault(k, len(index)) for k in keys), dtype=np.intp, count=len(keys)
    )
    order = np.argsort(gid, kind="stable")
    sizes = np.bincount(gid, minlength=len(index))
    starts = np.concatenate(([0], np.cumsum(sizes)[:-1]))
    stats: dict[str, tuple] = {}
    for f in SUMMARY_FIELDS:
        col = columns.get(f)
        if col is None:
            continue
        x = np.asarray(col, dtype=float)[order]  # None -> nan, booleans -> 0/1
        ok = ~np.isnan(x)
        n = np.add.reduceat(ok.astype(np.int64), starts)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            mean = np.add.reduceat(np.where(ok, x, 0.0), starts) / n
            dev = np.where(ok, x - np.repeat(mean, sizes), 0.0)
            std = np.sqrt(np.add.reduceat(dev * dev, starts) / n)
        over = (n > 0) & ~(np.isfinite(mean) & np.isfinite(std))
        if over.any():
            mean, std = _scaled_stats(x, ok, starts, sizes, n, mean, std, over)
        stats[f] = (mean.tolist(), std.tolist(), n.tolist())
    out = []
    for key in sorted(index, key=lambda k: tuple((v is None, v) for v in k)):
        g = index[key]
        group_stats = {}
        for f in SUMMARY_FIELDS:
            if f not in stats or stats[f][2][g] == 0:
                group_stats[f] = {"mean": None, "std": None, "count": 0}
            else:
                mean, std, n = stats[f]
                group_stats[f] = stat_entry(mean[g], std[g], n[g])
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
