"""Chart data of the job page, from the stored summaries (never the result rows).

A summary group is one (system, σ_w, N, estimator, γ) with ``stats[field] = {mean,
std, count}`` (std with ddof 0, docs/spec.md#summaries). A chart puts one grid coordinate
on the x axis (N, σ_w or γ); each remaining combination of system, σ_w and N is a
panel, and each (estimator, γ) a line of a panel. OLS has no γ: against γ it is a
flat reference line at its value for that panel.
"""

from __future__ import annotations

import math
from collections import defaultdict

from sqlalchemy.orm import Session

from service.db.result_queries import summary_metrics, summary_stats
from service.web import fields
from svrobs_core.records import SUMMARY_FIELDS

X_FIELDS = ("N", "sigma_w", "gamma")
PANEL_FIELDS = ("system", "sigma_w", "N")
LABELS = {"N": "N", "sigma_w": "σ_w", "gamma": "γ", "system": "system"}


class ChartError(ValueError):
    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


def check(metric: str, x: str) -> None:
    """ChartError naming the parameter unless ``metric`` is a summary field and ``x``
    one of X_FIELDS."""
    if x not in X_FIELDS:
        raise ChartError("x", f"must be one of {', '.join(X_FIELDS)}")
    if metric not in SUMMARY_FIELDS:
        raise ChartError("metric", "must be a numeric record field of the summaries")


def stored_groups(session: Session, job_id: int, *fields: str) -> list[dict]:
    """The job's summary groups with the stats of ``fields`` only: the database takes
    those fields out of each row's stats (the rest is never decoded)."""
    for f in fields:
        check(f, "N")
    return summary_stats(session, job_id, fields)


def stored_metrics(session: Session, job_id: int) -> list[str]:
    """Summary fields with a non-null mean in at least one of the job's groups."""
    return summary_metrics(session, job_id)


def finite(v) -> float | None:
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


def fmt(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def _series_label(estimator: str, gamma, x: str) -> str:
    if x == "gamma":
        return f"{estimator} (no γ)" if estimator == "ols" else estimator
    return estimator if gamma is None else f"{estimator} γ={fmt(gamma)}"


def chart_data(groups: list[dict], *, metric: str, x: str) -> dict:
    """Panels of ``metric`` against ``x``: ``{panels: [{key, title, x, series: [{label,
    estimator, gamma, mean, std, count, flat}]}], positive}``; a missing group
    or a null mean is None at its x."""
    check(metric, x)
    panel_fields = [f for f in PANEL_FIELDS if f != x]
    panels: dict[tuple, dict[tuple, dict]] = defaultdict(dict)
    xs: dict[tuple, set] = defaultdict(set)
    for g in groups:
        pkey = tuple(g[f] for f in panel_fields)
        gamma = None if x == "gamma" else g["gamma"]
        skey = (g["estimator"] != "ols", g["estimator"], gamma if gamma is not None else -1.0)
        s = (g.get("stats") or {}).get(metric) or {}
        xv = g[x]
        if xv is not None:
            xs[pkey].add(xv)
        panels[pkey].setdefault(skey, {})[xv] = s
    out, positive = [], True
    for pkey in sorted(panels):
        xvals = sorted(xs[pkey])
        series = []
        for skey in sorted(panels[pkey]):
            by_x = panels[pkey][skey]
            flat = x == "gamma" and set(by_x) == {None}  # OLS against γ
            cells = [by_x[None] if flat else by_x.get(v, {}) for v in xvals]
            mean = [finite(c.get("mean")) for c in cells]
            positive &= all(m is None or m > 0 for m in mean)
            series.append(
                {
                    "label": _series_label(skey[1], None if skey[2] == -1.0 else skey[2], x),
                    "estimator": skey[1],
                    "gamma": None if skey[2] == -1.0 else skey[2],
                    "mean": mean,
                    "std": [finite(c.get("std")) for c in cells],
                    "count": [c.get("count", 0) for c in cells],
                    "flat": flat,
                }
            )
        coords = dict(zip(panel_fields, pkey))
        title = " · ".join(
            f"{LABELS[f]} = {fields.coordinate(f, v) or fmt(v)}" for f, v in coords.items()
        )
        key = "|".join(map(str, pkey))
        out.append({"key": key, "title": title, "coords": coords, "x": xvals, "series": series})
    return {
        "metric": metric,
        "x": x,
        "x_label": LABELS[x],
        "panels": out,
        "positive": positive and bool(out),
    }
