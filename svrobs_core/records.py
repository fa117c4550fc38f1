"""The result record of SPEC section 10: field names, JSON-safe values, summary."""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

KEY_FIELDS = ("system", "sigma_w", "N", "N0", "estimator", "gamma", "rep", "seed_key")
ESTIMATE_FIELDS = ("A_hat", "B_hat", "rmse_A", "rmse_B")
BOUND_FIELDS = (
    "H_A", "H_B", "r_A", "r_B", "eps_A", "eps_B", "coverage_A", "coverage_B",
    "thm1_holds_A", "thm1_holds_B", "rho_upper_bound", "stable_certified",
)
GAIN_FIELDS = ("L", "g_L", "certified", "rho_true", "K")
COST_FIELDS = (
    "J_exact", "J_stationary", "J_mc", "J_mc_se", "J_star", "cost_ratio", "J_bound", "delta_J",
)
SLS_FIELDS = ("J_opt", "J_opt_bound", "sls_status")
RECORD_FIELDS = (
    KEY_FIELDS + ESTIMATE_FIELDS + BOUND_FIELDS + GAIN_FIELDS + COST_FIELDS + SLS_FIELDS + ("notes",)
)
MATRIX_FIELDS = ("A_hat", "B_hat", "L", "K")
BOOL_FIELDS = ("thm1_holds_A", "thm1_holds_B", "stable_certified", "certified")
TEXT_FIELDS = ("system", "estimator", "sls_status", "notes")
# Scalars a user filters, sorts and averages on: one numeric SQL column each.
NUMERIC_FIELDS = tuple(
    f for f in RECORD_FIELDS
    if f not in MATRIX_FIELDS + TEXT_FIELDS + ("seed_key",)
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


def summarize(records) -> list[dict]:
    """Mean, std (ddof=0) and count of every numeric field per group (GROUP_FIELDS).

    Booleans count as 0/1, nulls are skipped. Returns one dict per group:
    ``{system, sigma_w, N, estimator, gamma, count, stats: {field: {mean, std, count}}}``.
    """
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in records:
        groups[tuple(r[g] for g in GROUP_FIELDS)].append(r)
    out = []
    for key in sorted(groups, key=lambda k: tuple((v is None, v) for v in k)):
        rows = groups[key]
        stats = {}
        for f in NUMERIC_FIELDS:
            if f in ("N", "N0", "rep", "sigma_w", "gamma"):
                continue
            vals = np.array([float(r[f]) for r in rows if r.get(f) is not None], dtype=float)
            if vals.size:
                stats[f] = {
                    "mean": float(vals.mean()),
                    "std": float(vals.std()),
                    "count": int(vals.size),
                }
            else:
                stats[f] = {"mean": None, "std": None, "count": 0}
        out.append({**dict(zip(GROUP_FIELDS, key)), "count": len(rows), "stats": stats})
    return out
