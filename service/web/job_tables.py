"""Table 2 and the RMSE findings of the job page, from the stored summaries,
never from the result rows.

Table 2 (docs/science.md#9-the-papers-section-6-as-a-preset) is, per system, σ_w and matrix,
the mean over the N grid of
the mean over the repetitions at each N. A summary group is one (system, σ_w, N,
estimator, γ) and its ``mean`` is that mean over the repetitions, so a group taken
as one record carrying its means gives the report's own :func:`table2` and finding
the same numbers (a mean over one value is the value); only the repetition counts
come from the groups' ``count``. Everything else in the findings needs the cell
rows (quantiles, shares, matrices): the full report has it.
"""

from __future__ import annotations

import math

from svrobs_core.report import TABLE2_COLUMNS, table2
from svrobs_core.report.columns import GAMMA_RTOL, Columns
from svrobs_core.report.findings import _f_svr_vs_ols

TABLE_FIELDS = ("rmse_A", "rmse_B")
# the job page shows our numbers only: the paper's published values, and whether this
# grid is the paper's, are the full report's
PAGE_COLUMNS = tuple(c for c in TABLE2_COLUMNS if not c.startswith(("paper_", "ratio_")))


def group_columns(groups: list[dict]) -> Columns:
    """One record per summary group, its fields set to the group's means (no matrices)."""
    records = [
        {
            **{k: g[k] for k in ("system", "sigma_w", "N", "estimator", "gamma")},
            **{f: (s or {}).get("mean") for f, s in (g.get("stats") or {}).items()},
        }
        for g in groups
    ]
    return Columns.from_records(records, matrices=False)


def _least_counts(groups: list[dict]) -> dict[tuple, int]:
    """(system, σ_w, matrix, estimator, γ) -> the fewest repetitions with an RMSE at
    any N."""
    least: dict[tuple, int] = {}
    for g in groups:
        for mat in ("A", "B"):
            n = ((g.get("stats") or {}).get(f"rmse_{mat}") or {}).get("count")
            if n:
                k = (g["system"], g["sigma_w"], mat, g["estimator"], g["gamma"])
                least[k] = min(least.get(k, n), n)
    return least


def _reps(least: dict[tuple, int], row: dict) -> int:
    """Table 2's reps_per_N: the fewest over the row's OLS and SVR (row γ) groups."""
    g = row["gamma"]
    n = [
        c
        for (system, sigma_w, mat, est, gamma), c in least.items()
        if (system, sigma_w, mat) == (row["system"], row["sigma_w"], row["matrix"])
        if est == "ols"
        or (g is not None and gamma is not None and math.isclose(gamma, g, rel_tol=GAMMA_RTOL))
    ]
    return min(n, default=0)


def summary_tables(groups: list[dict]) -> tuple[list[dict], list[str]]:
    """:func:`svrobs_core.report.table2` (restricted to PAGE_COLUMNS) and the report's
    findings that rest on mean RMSE only (SVR against OLS, and the paper's claim at
    the largest σ_w), from summary groups with ``rmse_A``/``rmse_B`` stats."""
    if not groups:
        return [], []
    cols, least = group_columns(groups), _least_counts(groups)
    rows = [
        {**{c: r[c] for c in PAGE_COLUMNS}, "reps_per_N": _reps(least, r)} for r in table2(cols)
    ]
    return rows, _f_svr_vs_ols(cols)
