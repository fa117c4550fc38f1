"""Table 2 and the RMSE findings of the job page, from the stored summaries (issue 11),
never from the result rows.

Table 2 (SPEC section 9) is, per system, σ_w and matrix, the mean over the N grid of
the mean over the repetitions at each N. A summary group is one (system, σ_w, N,
estimator, γ) and its ``mean`` is that mean over the repetitions, so a group taken
as one record carrying its means gives the report's own :func:`table2` and finding
the same numbers (a mean over one value is the value); only the repetition counts
come from the groups' ``count``. Everything else in the findings needs the cell
rows (quantiles, shares, matrices): the full report has it.
"""

from __future__ import annotations

from svrobs_core.report import TABLE2_COLUMNS, table2
from svrobs_core.report.columns import GAMMA_RTOL, as_columns
from svrobs_core.report.findings import _f_svr_vs_ols

TABLE_FIELDS = ("rmse_A", "rmse_B")
# the job page shows our numbers only: the paper's published values, and whether this
# grid is the paper's, are the full report's
PAGE_COLUMNS = tuple(c for c in TABLE2_COLUMNS if not c.startswith(("paper_", "ratio_")))


def group_records(groups: list[dict]) -> list[dict]:
    """One record per summary group, its fields set to the group's means."""
    return [
        {
            **{k: g[k] for k in ("system", "sigma_w", "N", "estimator", "gamma")},
            **{f: (s or {}).get("mean") for f, s in (g.get("stats") or {}).items()},
        }
        for g in groups
    ]


def _reps(groups: list[dict], row: dict) -> int:
    """Table 2's reps_per_N: the fewest repetitions with a value at any N, over the
    OLS and the SVR (row γ) groups of the row."""
    f = f"rmse_{row['matrix']}"
    least = {}
    for g in groups:
        st = (g.get("stats") or {}).get(f) or {}
        if g["system"] != row["system"] or g["sigma_w"] != row["sigma_w"] or not st.get("count"):
            continue
        if g["estimator"] == "svr" and not (
            row["gamma"] is not None
            and g["gamma"] is not None
            and abs(g["gamma"] - row["gamma"]) <= GAMMA_RTOL * abs(row["gamma"])
        ):
            continue
        least[g["estimator"]] = min(least.get(g["estimator"], st["count"]), st["count"])
    return min(least.values(), default=0)


def summary_table2(groups: list[dict]) -> list[dict]:
    """:func:`svrobs_core.report.table2` from summary groups (with ``rmse_A``/``rmse_B``
    stats), restricted to PAGE_COLUMNS."""
    rows = table2(group_records(groups))
    return [{**{c: r[c] for c in PAGE_COLUMNS}, "reps_per_N": _reps(groups, r)} for r in rows]


def summary_findings(groups: list[dict]) -> list[str]:
    """The report's findings that rest on mean RMSE only (SVR against OLS, and the
    paper's claim at the largest σ_w), from summary groups."""
    return _f_svr_vs_ols(as_columns(group_records(groups)))
