"""Table 2: our OLS and SVR RMSE beside the paper's published values
(docs/science.md#92-how-the-tables-and-figures-aggregate).

:func:`table2` -> rows; :func:`table2_markdown` and :func:`table2_csv` render them.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable
from typing import Any

import numpy as np

from ..array_types import Array
from ..paper import TABLE2_GAMMA, published_table2, table2_grid_note
from .columns import (
    GAMMA_RTOL,
    Columns,
    as_columns,
    by_N,
    fmt_num,
    gammas_of,
    mean_of,
    select,
    sigmas_of,
    systems_of,
)


def table_gamma(cols: Columns, gamma: float | None) -> float | None:
    if gamma is not None:
        return float(gamma)
    gs = gammas_of(cols)
    if not gs:
        return None
    for g in gs:
        if math.isclose(g, TABLE2_GAMMA, rel_tol=GAMMA_RTOL):
            return g
    return gs[0]


def mean_over_reps_then_N(cols: Columns, mask: Array, f: str) -> tuple[float | None, int, int]:
    """Mean over repetitions per N, then mean over N
    (docs/science.md#92-how-the-tables-and-figures-aggregate)."""
    _, _, means, counts = by_N(cols, mask, cols[f], mean_of)
    ok = np.isfinite(means)
    if not ok.any():
        return None, 0, 0
    return float(means[ok].mean()), int(ok.sum()), int(counts[ok].min())


def table2(
    records: Columns | Iterable[dict[str, Any]], gamma: float | None = None, *, spec: Any = None
) -> list[dict[str, Any]]:
    """Table 2 rows: our OLS and SVR RMSE (mean over reps, then over the N grid)
    beside the paper's published values, with the ratio ours / paper.

    ``gamma``: the SVR gamma to tabulate (default 0.05 if present, else the
    first). Published values are attached only for gamma = 0.05 and the
    paper's systems, and, when the records' ``spec`` is given, only if its grid
    is the paper's (``paper.table2_grid_note``); otherwise every row's
    ``paper_note`` says why not.
    """
    cols = as_columns(records)
    g = table_gamma(cols, gamma)
    note = table2_grid_note(spec) if spec is not None else None
    rows = []
    for system in systems_of(cols):
        ms = select(cols, system=system)
        for sigma_w in sigmas_of(cols, ms):
            for mat in ("A", "B"):
                f = f"rmse_{mat}"
                m_ols = ms & select(cols, estimator="ols", sigma_w=sigma_w)
                if g is None:
                    m_svr = np.zeros(cols.n, bool)
                else:
                    m_svr = ms & select(cols, estimator="svr", gamma=g, sigma_w=sigma_w)
                ols, nN_o, nr_o = mean_over_reps_then_N(cols, m_ols, f)
                svr, nN_s, nr_s = mean_over_reps_then_N(cols, m_svr, f)
                pub = None
                if (
                    note is None
                    and g is not None
                    and math.isclose(g, TABLE2_GAMMA, rel_tol=GAMMA_RTOL)
                ):
                    pub = published_table2(system, sigma_w, mat)
                p_ols = pub["ols"] if pub else None
                p_svr = pub["ours"] if pub else None
                rows.append(
                    {
                        "system": system,
                        "sigma_w": sigma_w,
                        "matrix": mat,
                        "gamma": g,
                        "ols": ols,
                        "svr": svr,
                        "paper_ols": p_ols,
                        "paper_ours": p_svr,
                        "ratio_ols": (ols / p_ols) if (ols is not None and p_ols) else None,
                        "ratio_svr": (svr / p_svr) if (svr is not None and p_svr) else None,
                        "svr_minus_ols": (svr - ols)
                        if (svr is not None and ols is not None)
                        else None,
                        "n_N": max(nN_o, nN_s),
                        "reps_per_N": min((x for x in (nr_o, nr_s) if x), default=0),
                        "paper_note": note,
                    }
                )
    return rows


TABLE2_COLUMNS = (
    "system",
    "sigma_w",
    "matrix",
    "gamma",
    "ols",
    "svr",
    "paper_ols",
    "paper_ours",
    "ratio_ols",
    "ratio_svr",
    "svr_minus_ols",
    "n_N",
    "reps_per_N",
)


def table2_markdown(rows: list[dict[str, Any]]) -> str:
    head = (
        "| System | σ_w | Matrix | OLS (ours) | SVR (ours) | OLS (paper, published) "
        '| "Ours" SVR (paper, published) | OLS ours/paper | SVR ours/paper '
        "| SVR − OLS (ours) |"
    )
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        lines.append(
            f"| {r['system']} | {fmt_num(r['sigma_w'])} | {r['matrix']} | {fmt_num(r['ols'])} "
            f"| {fmt_num(r['svr'])} | {fmt_num(r['paper_ols'])} | {fmt_num(r['paper_ours'])} "
            f"| {fmt_num(r['ratio_ols'], 3)} | {fmt_num(r['ratio_svr'], 3)} "
            f"| {fmt_num(r['svr_minus_ols'], 3)} |"
        )
    if rows:
        g = rows[0].get("gamma")
        n_N = max(r["n_N"] for r in rows)
        reps = min((r["reps_per_N"] for r in rows if r["reps_per_N"]), default=0)
        lines.append("")
        lines.append(
            f"RMSE = sqrt(mean of squared entry errors) of one estimate, averaged over the "
            f"{reps} repetitions at each N and then over the {n_N} values of N "
            "(docs/science.md#92-how-the-tables-and-figures-aggregate); "
            f"SVR with γ = {fmt_num(g)}. The paper columns are the paper's "
            f"published Table 2 values, not results of this run."
            + (f" {rows[0]['paper_note']}" if rows[0].get("paper_note") else "")
        )
    return "\n".join(lines) + "\n"


def table2_csv(rows: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(TABLE2_COLUMNS), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in TABLE2_COLUMNS})
    return buf.getvalue()
