"""What each figure plots, as data: :data:`FIGURE_SERIES`, one row per plotted quantity.

A row says which record field (or quantity derived from several fields) is
drawn, which statistic of it over the repetitions at each N, which records
(``where``), which fields split it into panels and into lines, the band
around it and the reference of its difference panel. The report's figures
compute their curves from these rows (:func:`series_lines`); the dashboard's
charts read the same rows (``to_dict()`` is JSON) so both show the same
series, grouping and bands.

Symbolic values in ``where``: ``"table"`` (γ of Table 2, 0.05, for SVR; OLS
has no γ), ``"sigma_ref"`` (σ_w = 1 if present), ``"gamma_ref"`` (the spec's
γ_ref), ``"system_S"`` (the stable system). ``stat``: ``mean`` (over the
repetitions at one N), ``share_negative`` (share of repetitions < 0),
``ratio_of_means`` (|mean_γ − mean_ref| / mean_ref,
docs/science.md#92-how-the-tables-and-figures-aggregate; computable
from summaries' means). ``derived`` rows need the records (matrices), not the
summaries.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ..array_types import Array
from ..paper import STABLE, TABLE2_GAMMA
from .columns import GAMMA_RTOL, Columns, Meta, by_N, group_indices, mean_of, select


@dataclass(frozen=True)
class FigureSeries:
    figure: str
    key: str  # unique within the figure
    field: str  # a record field, or a name in DERIVED
    label: str
    stat: str = "mean"
    where: tuple[tuple[str, Any], ...] = ()  # ((field, value), ...)
    panels: tuple[str, ...] = ("system",)
    lines: tuple[str, ...] = ("gamma",)
    x: str = "N0"  # summaries hold N; N0 = (T0 − 1)·N
    band: tuple[float, float] | None = None  # (lower, upper) quantiles over the repetitions
    scale: str = "auto"  # auto: log if positive, symlog if the values change sign
    # difference panel: each line minus the "ols" line or the "first" line (smallest γ)
    diff_to: str | None = None

    @property
    def derived(self) -> bool:
        return self.field in DERIVED

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["where"] = dict(self.where)
        d["derived"] = self.derived
        return d


def _fs(figure: str, key: str, field: str, label: str, **kw: Any) -> FigureSeries:
    return FigureSeries(figure, key, field, label, **kw)


_SVR_TABLE = (("estimator", "svr"), ("gamma", "table"))
_E2 = (("estimator", "svr"), ("sigma_w", "sigma_ref"))
_S = (("estimator", "svr"), ("system", "system_S"))
_AUDIT = (("sigma_w", "sigma_ref"), ("gamma", "table"))  # SVR at the table's γ, and OLS


def _entry_rows(
    figure: str, where: tuple[tuple[str, Any], ...], lines: tuple[str, ...], diff: str | None
) -> list[FigureSeries]:
    rows: list[FigureSeries] = []
    for m in ("A", "B"):
        rows += [
            _fs(
                figure,
                f"err_{m}",
                f"entry_error_{m}",
                f"max_ij |Δ{m}_ij|",
                where=where,
                lines=lines,
                diff_to=diff,
            ),
            _fs(
                figure,
                f"hi_{m}",
                f"interval_hi_{m}",
                "upper interval end",
                where=where,
                lines=lines,
            ),
            _fs(
                figure,
                f"lo_{m}",
                f"neg_interval_lo_{m}",
                "−(lower interval end)",
                where=where,
                lines=lines,
            ),
            _fs(figure, f"eps_{m}", f"eps_{m}", f"ε_{m} (Corollary 1)", where=where, lines=lines),
        ]
    return rows


FIGURE_SERIES: tuple[FigureSeries, ...] = (
    *(
        _fs(
            "fig_rmse",
            f"rmse_{m}",
            f"rmse_{m}",
            f"RMSE of {m}̃",
            where=(("gamma", "table"),),
            lines=("sigma_w", "estimator"),
            diff_to="ols",
        )
        for m in ("A", "B")
    ),
    *_entry_rows("fig2", _SVR_TABLE, ("sigma_w",), None),
    *_entry_rows("fig3", _E2, ("gamma",), "first"),
    _fs("fig4", "delta_J", "delta_J", "ΔJ = J_b − J", where=_S, band=(0.05, 0.95), diff_to="first"),
    _fs(
        "fig4",
        "share_neg",
        "delta_J",
        "share of repetitions with ΔJ < 0",
        stat="share_negative",
        where=_S,
        scale="linear",
    ),
    _fs(
        "fig5",
        "ratio",
        "J_exact",
        "r = |J̄_γ − J̄_ref| / J̄_ref",
        stat="ratio_of_means",
        where=(("estimator", "svr"),),
        diff_to="first",
    ),
    _fs(
        "fig5",
        "ratio_rep",
        "cost_ratio",
        "mean of per-repetition cost_ratio",
        where=(("estimator", "svr"),),
    ),
    *(
        _fs(
            "fig_coverage",
            f"coverage_{m}",
            f"coverage_{m}",
            f"coverage of the {m}_ij intervals",
            panels=("system", "sigma_w"),
            lines=("estimator", "gamma"),
            scale="linear",
        )
        for m in ("A", "B")
    ),
    _fs(
        "fig_certified",
        "certified",
        "certified",
        "certified: g(L) < 1",
        where=(("estimator", "svr"),),
        scale="linear",
    ),
    _fs(
        "fig_certified",
        "stable_true",
        "stable_true",
        "ρ(A − LC) < 1 for the true A",
        where=(("estimator", "svr"),),
        scale="linear",
    ),
    _fs(
        "fig_svr_ols_diff",
        "svr_ols_A",
        "svr_ols_diff_A",
        "max_ij |Ã_SVR − Ã_OLS|",
        where=(("estimator", "svr"),),
        lines=("gamma", "sigma_w"),
    ),
    # the uncertainty-set audit: one set of these lines per bounds_method,
    # each from its own experiment (a job has one bounds_method)
    _fs(
        "fig_bounds_audit",
        "all_inside",
        "all_inside",
        "share of records with every entry of A and of B inside",
        where=_AUDIT,
        lines=("estimator",),
        scale="linear",
    ),
    _fs(
        "fig_bounds_audit",
        "r_A",
        "r_A",
        "r_A (largest entry radius of A)",
        where=_AUDIT,
        lines=("estimator",),
    ),
)


def figure_series(figure: str) -> dict[str, FigureSeries]:
    """The rows of one figure, by key."""
    return {s.key: s for s in FIGURE_SERIES if s.figure == figure}


def figure_series_json() -> list[dict[str, Any]]:
    """:data:`FIGURE_SERIES` as JSON-able dicts (for the dashboard)."""
    return [s.to_dict() for s in FIGURE_SERIES]


# ---------------------------------------------------------------------------
# derived quantities (per record)
# ---------------------------------------------------------------------------


# A DERIVED quantity: (columns, meta, matrix "A"/"B" or None) -> per-record values.
DerivedFn = Callable[[Columns, Meta, str | None], Array]


def _entry(i: int) -> DerivedFn:
    def f(cols: Columns, meta: Meta, m: str | None) -> Array:
        from .derived import entry_quantities

        assert m is not None  # the entry rows name their matrix
        return entry_quantities(cols, meta, m)[i]

    return f


def _neg(fn: DerivedFn) -> DerivedFn:
    return lambda cols, meta, m: -fn(cols, meta, m)


def _svr_ols(cols: Columns, meta: Meta, m: str | None) -> Array:
    from .derived import svr_ols_diff

    return svr_ols_diff(cols)


def _all_inside(cols: Columns, meta: Meta, m: str | None) -> Array:
    from .derived import all_inside

    return all_inside(cols)


def _stable_true(cols: Columns, meta: Meta, m: str | None) -> Array:
    rho = cols["rho_true"]
    return np.where(np.isfinite(rho), (rho < 1).astype(float), np.nan)


DERIVED: dict[str, tuple[DerivedFn, str | None]] = {
    **{f"entry_error_{m}": (_entry(0), m) for m in ("A", "B")},
    **{f"interval_lo_{m}": (_entry(1), m) for m in ("A", "B")},
    # minus the lower end: positive when the interval reaches below 0, so that the
    # ends share one log axis with the error and ε
    **{f"neg_interval_lo_{m}": (_neg(_entry(1)), m) for m in ("A", "B")},
    **{f"interval_hi_{m}": (_entry(2), m) for m in ("A", "B")},
    "svr_ols_diff_A": (_svr_ols, "A"),
    "stable_true": (_stable_true, None),
    "all_inside": (_all_inside, None),
}


def values_of(cols: Columns, meta: Meta, field: str) -> np.ndarray:
    """Per-record values of a field or a DERIVED quantity (cached per Columns)."""
    if field not in DERIVED:
        return cols[field] if field in cols.data else np.full(cols.n, np.nan)
    key = ("derived", field)
    if key not in cols.cache:
        fn, m = DERIVED[field]
        cols.cache[key] = fn(cols, meta, m)
    values: np.ndarray = cols.cache[key]
    return values


# ---------------------------------------------------------------------------
# selection and lines
# ---------------------------------------------------------------------------


@dataclass
class Line:
    """One plotted line: its group key, x (N0), N, the statistic and the band."""

    key: dict[str, Any]
    x: np.ndarray
    N: np.ndarray
    y: np.ndarray
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None
    count: np.ndarray | None = None


def resolve(value: Any, ctx: dict[str, Any]) -> Any:
    """A ``where`` value with the symbols resolved from ``ctx`` (table_gamma, ...)."""
    return ctx.get(value, value) if isinstance(value, str) else value


def where_mask(cols: Columns, s: FigureSeries, ctx: dict[str, Any]) -> np.ndarray:
    """The records of row ``s``; a γ condition selects among the SVR records
    (OLS has no γ and passes it, unless ``estimator`` excludes it)."""
    m = np.ones(cols.n, bool)
    for f, v in s.where:
        v = resolve(v, ctx)
        if f == "gamma":
            m &= np.isnan(cols["gamma"]) | (select(cols, gamma=v) if v is not None else False)
        elif v is None:
            m &= False
        else:
            m &= select(cols, **{f: v})
    return m


def context(cols: Columns, meta: Meta, **over: Any) -> dict[str, Any]:
    """The symbols of ``where``: table γ, reference σ_w, γ_ref, the stable system."""
    from .columns import sigmas_of, systems_of
    from .tables import table_gamma

    sig = sigmas_of(cols)
    systems = systems_of(cols)
    ctx: dict[str, Any] = {
        "table": table_gamma(cols, None),
        "sigma_ref": 1.0 if any(math.isclose(s, 1.0) for s in sig) else (sig[0] if sig else None),
        "gamma_ref": meta.gamma_ref,
        "system_S": STABLE if STABLE in systems or not systems else systems[0],
    }
    ctx.update({k: v for k, v in over.items() if v is not None})
    if ctx["table"] is None:
        ctx["table"] = TABLE2_GAMMA
    return ctx


def _share_negative(v: Array) -> float:
    return float(np.mean(v < 0))


def _quantile(q: float) -> Callable[[Array], float]:
    return lambda v: float(np.quantile(v, q))


def series_lines(
    cols: Columns, meta: Meta, s: FigureSeries, panel_mask: Array, ctx: dict[str, Any]
) -> list[Line]:
    """The lines of row ``s`` inside one panel (``panel_mask``), one per group of
    ``s.lines``, in the groups' order; lines without a finite value are left out."""
    m = panel_mask & where_mask(cols, s, ctx)
    if s.stat == "ratio_of_means":
        return _ratio_lines(cols, s, m, ctx)
    vals = values_of(cols, meta, s.field)
    out: list[Line] = []
    fn = {"mean": mean_of, "share_negative": _share_negative}[s.stat]
    for key, idx in group_indices(cols, s.lines, m).items():
        x, N, y, cnt = by_N(cols, idx, vals, fn)
        if not np.isfinite(y).any():
            continue
        line = Line(dict(zip(s.lines, key)), x, N, y, count=cnt)
        if s.band is not None:
            qlo, qhi = s.band
            line.lo = by_N(cols, idx, vals, _quantile(qlo))[2]
            line.hi = by_N(cols, idx, vals, _quantile(qhi))[2]
        out.append(line)
    return out


def _ratio_lines(cols: Columns, s: FigureSeries, m: Array, ctx: dict[str, Any]) -> list[Line]:
    """|mean_γ − mean_ref| / mean_ref per N
    (docs/science.md#92-how-the-tables-and-figures-aggregate), γ ≠ γ_ref."""
    from .derived import ratio_to_reference

    vals = cols[s.field]
    groups = group_indices(cols, ("gamma",), m & np.isfinite(vals))
    g_ref = ctx["gamma_ref"]
    ref = [k for k in groups if k[0] is not None and math.isclose(k[0], g_ref, rel_tol=GAMMA_RTOL)]
    if not ref:
        return []
    rm = np.zeros(cols.n, bool)
    rm[groups[ref[0]]] = True
    out: list[Line] = []
    for key, idx in groups.items():
        if key != ref[0]:
            gm = np.zeros(cols.n, bool)
            gm[idx] = True
            x, N, r, cnt = ratio_to_reference(cols, gm, rm, vals)
            out.append(Line({"gamma": key[0]}, x, N, r, count=cnt))
    return out


# ---------------------------------------------------------------------------
# the same rows on stored summaries (for the dashboard)
# ---------------------------------------------------------------------------


def _matches(g: dict[str, Any], f: str, v: Any) -> bool:
    if f == "gamma":  # selects among the SVR groups; OLS has no γ
        return g["gamma"] is None or (
            v is not None and math.isclose(g["gamma"], v, rel_tol=GAMMA_RTOL)
        )
    if v is None:
        return False
    if isinstance(v, float) and g[f] is not None and not isinstance(g[f], str):
        return math.isclose(g[f], v, rel_tol=GAMMA_RTOL)
    same: bool = g[f] == v
    return same


def summary_lines(
    groups: list[dict[str, Any]], s: FigureSeries, ctx: dict[str, Any]
) -> list[dict[str, Any]]:
    """Row ``s`` on summary groups (``svrobs_core.summarize`` / the stored
    summaries: one dict per (system, σ_w, N, estimator, γ) with ``stats[field]``
    mean/std/count): ``[{"panel": {...}, "line": {...}, "N": [...], "y": [...]}]``
    with the row's statistic per N; the same curves as :func:`series_lines` for
    ``stat`` "mean" and "ratio_of_means" (x is N here; N0 = (T0 − 1)·N). Rows the
    summaries cannot give (``derived``, ``share_negative``) -> ValueError."""
    if s.derived or s.stat not in ("mean", "ratio_of_means"):
        raise ValueError(f"{s.figure}/{s.key}: needs the records, not the summaries")
    where = [(f, resolve(v, ctx)) for f, v in s.where]
    # (panel, line, N) -> [sum, count]: groups that differ only in a coordinate the row
    # neither selects nor splits by (σ_w of Fig. 4) are pooled, as the records are
    acc: dict[tuple[Any, Any, Any], list[float]] = {}
    for g in groups:
        st = (g.get("stats") or {}).get(s.field) or {}
        if (
            st.get("mean") is None
            or not st.get("count")
            or not all(_matches(g, f, v) for f, v in where)
        ):
            continue
        a = acc.setdefault(
            (tuple(g[f] for f in s.panels), tuple(g[f] for f in s.lines), g["N"]), [0.0, 0]
        )
        a[0] += st["mean"] * st["count"]
        a[1] += st["count"]
    mean = {k: total / n for k, (total, n) in acc.items()}
    if s.stat == "ratio_of_means":  # each γ against γ_ref, per panel and N
        g_ref, gi = ctx["gamma_ref"], s.lines.index("gamma")

        def is_ref(k: tuple[Any, Any, Any]) -> bool:
            return k[1][gi] is not None and math.isclose(k[1][gi], g_ref, rel_tol=GAMMA_RTOL)

        ref = {(k[0], k[2]): v for k, v in mean.items() if is_ref(k)}
        mean = {
            k: abs(v - ref[k[0], k[2]]) / ref[k[0], k[2]]
            for k, v in mean.items()
            if ref.get((k[0], k[2])) and not is_ref(k)
        }
    out: dict[tuple[Any, Any], dict[Any, float]] = {}
    for (pk, lk, n), v in mean.items():
        out.setdefault((pk, lk), {})[n] = v
    lines: list[dict[str, Any]] = []

    def order(t: tuple[Any, Any]) -> tuple[tuple[bool, Any], ...]:
        return tuple((v is None, v if v is not None else 0) for part in t for v in part)

    for pk, lk in sorted(out, key=order):
        pts = sorted(out[(pk, lk)].items())
        lines.append(
            {
                "panel": dict(zip(s.panels, pk)),
                "line": dict(zip(s.lines, lk)),
                "N": [n for n, _ in pts],
                "y": [y for _, y in pts],
            }
        )
    return lines


GROUP_KEYS = ("system", "sigma_w", "N", "estimator", "gamma")


def summary_context(
    groups: list[dict[str, Any]], spec: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The symbols of ``where`` (as :func:`context`) from summary groups and the spec."""
    svr = sorted({g["gamma"] for g in groups if g["estimator"] == "svr" and g["gamma"] is not None})
    sig = sorted({g["sigma_w"] for g in groups if g["sigma_w"] is not None})
    systems = {g["system"] for g in groups}
    table = next((g for g in svr if math.isclose(g, TABLE2_GAMMA, rel_tol=GAMMA_RTOL)), None)
    return {
        "table": table if table is not None else (svr[0] if svr else TABLE2_GAMMA),
        "sigma_ref": 1.0 if any(math.isclose(x, 1.0) for x in sig) else (sig[0] if sig else None),
        "gamma_ref": float((spec or {}).get("gamma_ref", 0.1)),
        "system_S": STABLE if STABLE in systems or not systems else sorted(systems)[0],
    }
