"""The report's figure series as chart presets of the job page (the dashboard
and the figures share their choice of what to plot).

A preset is a row of :data:`svrobs_core.report.FIGURE_SERIES` that the stored
summaries can give (not ``derived``, statistic ``mean`` or ``ratio_of_means``). Its
curves are :func:`svrobs_core.report.summary_lines` on the stored summary groups, the
same series, grouping and selection as the report's figure; the y scale is the
row's (log when every value is positive, symlog sized to the data when values
change sign, else linear, as ``plotting.value_axis``). A row with a band gets one
here too, but the summaries hold no quantiles: it is mean ± std (ddof 0) over the
repetitions, and labelled so. x is N (the figures' N0 is (T0 − 1)·N).
"""

from __future__ import annotations

import math

import numpy as np

from service.web.charts import LABELS, ChartError, finite, fmt
from svrobs_core.report import FIGURE_SERIES, FigureSeries, summary_context, summary_lines
from svrobs_core.report.series import _matches, resolve

PRESETS: dict[str, FigureSeries] = {
    f"{s.figure}/{s.key}": s
    for s in FIGURE_SERIES
    if not s.derived and s.stat in ("mean", "ratio_of_means")
}
BAND_LABEL = "mean ± std over the repetitions (the summaries hold no quantiles)"


def preset_options() -> list[dict]:
    """The presets for the page's list: ``{id, figure, label, field}``."""
    return [
        {"id": pid, "figure": s.figure, "label": s.label, "field": s.field}
        for pid, s in PRESETS.items()
    ]


def preset_of(preset_id: str) -> FigureSeries:
    try:
        return PRESETS[preset_id]
    except KeyError:
        raise ChartError("preset", "must be one of the report's figure series") from None


def _title(coords: dict) -> str:
    return " · ".join(f"{LABELS.get(f, f)} = {fmt(v)}" for f, v in coords.items())


def _line_label(line: dict) -> str:
    parts = []
    for f, v in line.items():
        if f == "gamma" and v is None:
            parts.append("(no γ)")
        elif f == "estimator":
            parts.append(str(v))
        else:
            parts.append(f"{LABELS.get(f, f)}={fmt(v)}")
    return " ".join(parts) or "all"


def _pooled_std(members: list[dict], field: str) -> tuple[float | None, int]:
    """Std (ddof 0) and count of the repetitions of several groups pooled."""
    st = [(g.get("stats") or {}).get(field) or {} for g in members]
    st = [s for s in st if s.get("count") and s.get("mean") is not None]
    if not st or any(s.get("std") is None for s in st):
        return None, sum(s.get("count", 0) for s in st)
    n = np.array([s["count"] for s in st], float)
    m = np.array([s["mean"] for s in st], float)
    sd = np.array([s["std"] for s in st], float)
    mu = float(n @ m / n.sum())
    return finite(math.sqrt(float(n @ (sd**2 + (m - mu) ** 2) / n.sum()))), int(n.sum())


def y_scale(s: FigureSeries, values: list[float]) -> dict:
    """The row's y scale from the plotted values: log, symlog (linear region at the
    decade below the 10 % quantile of the nonzero |values|, as the figures) or linear."""
    v = np.array([x for x in values if x is not None], float)
    if s.scale == "linear" or v.size == 0:
        return {"scale": "linear"}
    if (v > 0).all():
        return {"scale": "log"}
    if (v < 0).any() and (v > 0).any():
        nz = np.abs(v[v != 0])
        return {
            "scale": "symlog",
            "linthresh": 10.0 ** math.floor(math.log10(np.quantile(nz, 0.1))),
        }
    return {"scale": "linear"}


def preset_chart(groups: list[dict], spec: dict | None, s: FigureSeries) -> dict:
    """Row ``s`` on the stored summary groups, in the shape of ``charts.chart_data``
    (panels of series with mean, std and count per x), plus its scale and band."""
    ctx = summary_context(groups, spec)
    lines = summary_lines(groups, s, ctx)
    where = [(f, resolve(v, ctx)) for f, v in s.where]
    by_point: dict[tuple, list[dict]] = {}  # the groups of one plotted point
    for g in groups:
        if all(_matches(g, f, v) for f, v in where):
            key = (*(g[f] for f in s.panels), *(g[f] for f in s.lines), g["N"])
            by_point.setdefault(key, []).append(g)
    band = s.band is not None and s.stat == "mean"
    panels: dict[tuple, dict] = {}
    for ln in lines:
        pkey = tuple(ln["panel"].values())
        panels.setdefault(pkey, {"coords": ln["panel"], "lines": []})["lines"].append(ln)
    out, values = [], []
    for pkey, p in panels.items():
        xs = sorted({n for ln in p["lines"] for n in ln["N"]})
        series: list[dict] = []
        colours: dict[tuple, int] = {}
        for ln in p["lines"]:
            # estimator lines of one other key share a colour, SVR dashed (as the figures)
            rest = tuple(v for f, v in ln["line"].items() if f != "estimator")
            colour = colours.setdefault(rest, len(colours))
            dashed = "estimator" in s.lines and ln["line"]["estimator"] == "svr" and bool(rest)
            y = dict(zip(ln["N"], ln["y"]))
            mean = [finite(y.get(n)) for n in xs]
            std, count = [], []
            for n in xs:
                members = by_point.get((*ln["panel"].values(), *ln["line"].values(), n), [])
                sd, cnt = _pooled_std(members, s.field)
                std.append(sd if band and n in y else None)
                count.append(cnt)
            values += [m for m in mean if m is not None]
            series.append(
                {
                    "label": _line_label(ln["line"]),
                    "estimator": ln["line"].get("estimator", "svr"),
                    "gamma": ln["line"].get("gamma"),
                    "line": ln["line"],
                    "mean": mean,
                    "std": std,
                    "count": count,
                    "flat": False,
                    "colour": colour if "estimator" in s.lines else None,
                    "dash": dashed,
                }
            )
        panel_key = "|".join(map(str, pkey))
        out.append(
            {
                "key": panel_key,
                "title": _title(p["coords"]),
                "coords": p["coords"],
                "x": xs,
                "series": series,
            }
        )
    return {
        "metric": s.label,
        "x": "N",
        "x_label": "N",
        "panels": out,
        "positive": bool(values) and all(v > 0 for v in values),
        "preset": {
            "figure": s.figure,
            "key": s.key,
            "field": s.field,
            "stat": s.stat,
            "band": BAND_LABEL if band else None,
        },
        **y_scale(s, values),
    }
