"""The report's figures: Figs. 2-5 of the paper and the figures beyond it.

Each is ``f(records, spec=None, *, experiment=...) -> matplotlib.figure.Figure``;
records are section 10 dicts or :class:`~svrobs_core.report.columns.Columns`.
"""

from __future__ import annotations

import math

import numpy as np

from ..paper import STABLE
from .columns import (
    GAMMA_RTOL,
    Columns,
    as_columns,
    by_N,
    fmt_num,
    gamma_label,
    gammas_of,
    mean_of,
    n0_ratio,
    select,
    sigmas_of,
    spec_meta,
    systems_of,
)
from .derived import cost_ratio_of_means, entry_quantities, first_stable_certified, svr_ols_diff
from .plotting import (
    figure_legend,
    figure_title,
    label_panel,
    legend_line,
    n0_axis,
    new_figure,
    no_data_panel,
    no_data_reason,
)
from .tables import table_gamma


def fig_rmse(records, spec=None, *, experiment: str | None = "E1", gamma: float | None = None):
    """RMSE of Ã and B̃ per N (the curves behind Table 2): OLS vs SVR, per σ_w."""
    cols, meta = as_columns(records), spec_meta(spec)
    g = table_gamma(cols, gamma)
    systems = systems_of(cols) or ["(none)"]
    fig, axes = new_figure(2, len(systems), (5.2 * len(systems), 7), sharex=True)
    sig = sigmas_of(cols)
    ratio = n0_ratio(cols)
    for c, system in enumerate(systems):
        for r, mat in enumerate(("A", "B")):
            ax = axes[r, c]
            f = f"rmse_{mat}"
            any_line = False
            for i, s in enumerate(sig):
                for est, ls in (("ols", "-"), ("svr", "--")):
                    m = select(
                        cols,
                        system=system,
                        estimator=est,
                        sigma_w=s,
                        gamma=None if est == "ols" else g,
                    )
                    x, _, y, _ = by_N(cols, m, cols[f], mean_of)
                    if np.isfinite(y).any():
                        ax.plot(x, y, color=f"C{i}", ls=ls, lw=1.3)
                        any_line = True
            if not any_line:
                no_data_panel(ax, no_data_reason(cols, select(cols, system=system), (f,), meta))
                continue
            ax.set_yscale("log")
            ax.minorticks_off()
            label_panel(
                ax, f"RMSE of {mat}̃ (mean over reps)", f"{system}: {mat}", ratio, xlabel=r == 1
            )
    handles = [legend_line(f"C{i}", "-", f"σ_w={fmt_num(s)}") for i, s in enumerate(sig)]
    handles += [legend_line("0.2", "-", "OLS"), legend_line("0.2", "--", f"SVR γ={fmt_num(g)}")]
    figure_legend(fig, handles, ncol=len(handles))
    figure_title(
        fig, f"RMSE per sample length behind Table 2 (OLS vs SVR γ={fmt_num(g)})", experiment, meta
    )
    return fig


def _interval_panels(
    fig, axes, cols, meta, series, series_label, systems, ratio, certified_marks=None
):
    """Shared body of fig2/fig3: rows A, B; columns systems; one color per series.

    series: list of (label, mask-builder(system) -> mask)."""
    q = {mat: entry_quantities(cols, meta, mat) for mat in ("A", "B")}
    for c, system in enumerate(systems):
        for r, mat in enumerate(("A", "B")):
            ax = axes[r, c]
            err, lo, hi = q[mat]
            any_line = False
            for i, (_label, mk) in enumerate(series):
                m = mk(system)
                x, _, y_err, _ = by_N(cols, m, err, mean_of)
                _, _, y_hi, _ = by_N(cols, m, hi, mean_of)
                _, _, y_lo, _ = by_N(cols, m, lo, mean_of)
                _, _, y_eps, _ = by_N(cols, m, cols[f"eps_{mat}"], mean_of)
                col = f"C{i}"
                for y, ls in ((y_err, "-"), (y_hi, "--"), (y_lo, "--"), (y_eps, ":")):
                    if np.isfinite(y).any():
                        ax.plot(x, y, color=col, ls=ls, lw=1.3)
                        any_line = True
                if certified_marks is not None and mat == "A":
                    mark = certified_marks(system, i)
                    if mark is not None:
                        ax.axvline(mark, color=col, ls=(0, (1, 2)), lw=2.2, alpha=0.8)
            if not any_line:
                no_data_panel(
                    ax,
                    no_data_reason(
                        cols,
                        _mask_any(series, system, cols.n),
                        (f"{mat}_hat", f"r_{mat}", f"eps_{mat}"),
                        meta,
                    ),
                )
                continue
            ax.axhline(0.0, color="0.5", lw=0.6)
            ax.set_yscale("symlog", linthresh=1e-2)
            ax.minorticks_off()
            label_panel(
                ax,
                f"{mat}: error / interval ends / ε_{mat}",
                f"{system}: {mat}",
                ratio,
                xlabel=r == 1,
            )


def _mask_any(series, system, n):
    m = np.zeros(n, bool)
    for _, mk in series:
        m |= mk(system)
    return m


def _style_handles(extra_vertical: bool = False):
    h = [
        legend_line("0.2", "-", "max_ij |ΔX_ij| (mean over reps)"),
        legend_line("0.2", "--", "Lemma 2 interval ends: max_ij γX̃_ij + r_X, min_ij γX̃_ij − r_X"),
        legend_line("0.2", ":", "ε_X (Corollary 1)"),
    ]
    if extra_vertical:
        from matplotlib.lines import Line2D

        h.append(
            Line2D(
                [],
                [],
                color="0.2",
                ls=(0, (1, 2)),
                lw=2.2,
                label="first N0 with stable_certified in ≥ half the reps (A row)",
            )
        )
    return h


def fig2(records, spec=None, *, experiment: str | None = "E1", gamma: float | None = None):
    """Fig. 2: SVR (γ = 0.05) estimation error and Lemma 2 interval ends vs N0,
    S and U, one color per σ_w; ε_A, ε_B of Corollary 1 dotted."""
    cols, meta = as_columns(records), spec_meta(spec)
    g = table_gamma(cols, gamma)
    systems = systems_of(cols) or ["(none)"]
    sig = sigmas_of(cols)
    fig, axes = new_figure(2, len(systems), (5.6 * len(systems), 8), sharex=True)
    series = (
        [
            (
                f"σ_w={fmt_num(s)}",
                (
                    lambda system, s=s: select(
                        cols, system=system, estimator="svr", gamma=g, sigma_w=s
                    )
                ),
            )
            for s in sig
        ]
        if g is not None
        else []
    )
    _interval_panels(fig, axes, cols, meta, series, "σ_w", systems, n0_ratio(cols))
    handles = [
        legend_line(f"C{i}", "-", lab) for i, (lab, _) in enumerate(series)
    ] + _style_handles()
    figure_legend(fig, handles, ncol=3)
    figure_title(
        fig,
        f"Fig. 2: SVR (γ={fmt_num(g)}) estimation error and Lemma 2 interval ends vs "
        f"sample length, for each σ_w",
        experiment,
        meta,
    )
    return fig


def fig3(records, spec=None, *, experiment: str | None = "E2", sigma_w: float | None = None):
    """Fig. 3: as Fig. 2 for the four gammas at one σ_w (default 1), with the
    first N0 at which stable_certified holds in ≥ half the reps ("never" else)."""
    cols, meta = as_columns(records), spec_meta(spec)
    sig = sigmas_of(cols)
    if sigma_w is None:
        sigma_w = 1.0 if any(math.isclose(s, 1.0) for s in sig) else (sig[0] if sig else None)
    systems = systems_of(cols) or ["(none)"]
    gs = gammas_of(cols)
    fig, axes = new_figure(2, len(systems), (5.6 * len(systems), 8.4), sharex=True)
    series = [
        (
            g,
            (
                lambda system, g=g: select(
                    cols, system=system, estimator="svr", gamma=g, sigma_w=sigma_w
                )
            ),
        )
        for g in gs
    ]
    first = first_stable_certified(cols) if sigma_w is not None else {}

    def mark(system, i):
        hit = first.get((system, sigma_w, "svr", gs[i]))
        return None if hit is None or hit["N0"] is None else hit["N0"]

    _interval_panels(
        fig, axes, cols, meta, series, "γ", systems, n0_ratio(cols), certified_marks=mark
    )
    handles = []
    for i, g in enumerate(gs):
        parts = []
        for system in systems:
            hit = first.get((system, sigma_w, "svr", g))
            if hit is None:
                parts.append(f"{system}: no data")
            elif hit["N0"] is None:
                parts.append(f"{system}: never (N0 ≤ {hit['N0_max']})")
            else:
                parts.append(f"{system}: from N0={hit['N0']}")
        handles.append(
            legend_line(f"C{i}", "-", f"γ={fmt_num(g)} — certified stable " + "; ".join(parts))
        )
    handles += _style_handles(extra_vertical=True)
    figure_legend(fig, handles, ncol=2)
    figure_title(
        fig,
        f"Fig. 3: SVR estimation error and Lemma 2 interval ends for each γ (σ_w={fmt_num(sigma_w)})",
        experiment,
        meta,
    )
    return fig


def _pick_system(cols: Columns, prefer: str, field_: str) -> str | None:
    systems = systems_of(cols)
    if prefer in systems:
        return prefer
    for s in systems:
        if cols.has(field_, select(cols, system=s)):
            return s
    return systems[0] if systems else None


def fig4(records, spec=None, *, experiment: str | None = "E3", system: str = STABLE):
    """Fig. 4: ΔJ = J_b − J vs N0 for each γ on S (mean, 5-95 % band), and the
    share of cells with ΔJ < 0."""
    cols, meta = as_columns(records), spec_meta(spec)
    system = _pick_system(cols, system, "delta_J")
    fig, axes = new_figure(1, 2, (12, 5))
    ax, ax2 = axes[0]
    ms = select(cols, system=system) if system else np.zeros(cols.n, bool)
    gs = gammas_of(cols, ms)
    ratio = n0_ratio(cols, ms)
    handles = []
    if not cols.has("delta_J", ms):
        reason = no_data_reason(cols, ms, ("delta_J", "J_bound", "J_exact"), meta)
        no_data_panel(ax, reason)
        no_data_panel(ax2, reason)
    else:
        dJ = cols["delta_J"]
        for i, g in enumerate(gs):
            m = ms & select(cols, estimator="svr", gamma=g)
            x, _, mean, _ = by_N(cols, m, dJ, mean_of)
            _, _, q05, _ = by_N(cols, m, dJ, lambda v: float(np.quantile(v, 0.05)))
            _, _, q95, _ = by_N(cols, m, dJ, lambda v: float(np.quantile(v, 0.95)))
            _, _, neg, _ = by_N(cols, m, dJ, lambda v: float(np.mean(v < 0)))
            n_neg = int(np.sum((dJ[m] < 0) & np.isfinite(dJ[m])))
            n_all = int(np.isfinite(dJ[m]).sum())
            ax.plot(x, mean, color=f"C{i}", lw=1.4)
            ax.fill_between(x, q05, q95, color=f"C{i}", alpha=0.15, lw=0)
            ax2.plot(x, neg, color=f"C{i}", lw=1.4)
            handles.append(
                legend_line(f"C{i}", "-", f"γ={fmt_num(g)} (ΔJ<0 in {n_neg} of {n_all} cells)")
            )
        ax.axhline(0, color="k", lw=0.8)
        ax.set_ylabel("ΔJ = J_b − J (mean over reps; band 5-95 %)")
        ax.set_yscale("symlog", linthresh=1e-2)
        ax.minorticks_off()
        ax2.set_ylabel("share of repetitions with ΔJ < 0")
        ax2.set_ylim(-0.02, 1.02)
        for a in (ax, ax2):
            n0_axis(a, ratio)
            a.grid(alpha=0.3)
        ax.set_title(f"{system}: bound minus exact cost", fontsize=10)
        ax2.set_title(f"{system}: where Theorem 3's bound fails", fontsize=10)
    figure_legend(fig, handles, ncol=2)
    figure_title(
        fig, f"Fig. 4: ΔJ = J_b − J vs sample length for each γ on {system}", experiment, meta
    )
    return fig


def fig5(records, spec=None, *, experiment: str | None = "E4"):
    """Fig. 5: cost ratio r = |mean J_γ − mean J_ref| / mean J_ref vs N0, S and U
    (solid); the mean of the per-repetition ``cost_ratio`` field dashed."""
    cols, meta = as_columns(records), spec_meta(spec)
    systems = systems_of(cols) or ["(none)"]
    g_ref = meta.gamma_ref
    fig, axes = new_figure(1, len(systems), (5.8 * len(systems), 5), sharey=True)
    gs = gammas_of(cols)
    handles = [
        legend_line(f"C{i}", "-", f"γ={fmt_num(g)}")
        for i, g in enumerate(gs)
        if not math.isclose(g, g_ref, rel_tol=GAMMA_RTOL)
    ]
    for c, system in enumerate(systems):
        ax = axes[0, c]
        ms = select(cols, system=system)
        if not cols.has("J_exact", ms):
            no_data_panel(ax, no_data_reason(cols, ms, ("J_exact",), meta))
            continue
        if not cols.has("J_exact", ms & select(cols, gamma=g_ref)):
            no_data_panel(ax, f"no J at the reference γ_ref={fmt_num(g_ref)}")
            continue
        for i, g in enumerate(gs):
            if math.isclose(g, g_ref, rel_tol=GAMMA_RTOL):
                continue
            x, _, r = cost_ratio_of_means(cols, system, g, g_ref)
            ax.plot(x, r, color=f"C{i}", lw=1.4)
            m = ms & select(cols, estimator="svr", gamma=g)
            if cols.has("cost_ratio", m):
                x2, _, y2, _ = by_N(cols, m, cols["cost_ratio"], mean_of)
                ax.plot(x2, y2, color=f"C{i}", lw=0.9, ls="--", alpha=0.7)
        ax.set_yscale("log")
        ax.minorticks_off()
        ylabel = f"r = |J_γ − J_ref| / J_ref  (γ_ref = {fmt_num(g_ref)})"
        label_panel(ax, ylabel, system, n0_ratio(cols, ms), grid="both")
    handles += [
        legend_line("0.2", "-", "ratio of the mean exact costs (SPEC 9)"),
        legend_line("0.2", "--", "mean of per-repetition cost_ratio"),
    ]
    figure_legend(fig, handles, ncol=len(handles))
    figure_title(
        fig,
        f"Fig. 5: observer cost ratio vs sample length (reference γ={fmt_num(g_ref)})",
        experiment,
        meta,
    )
    return fig


def fig_coverage(records, spec=None, *, experiment: str | None = "E2"):
    """Empirical coverage of the Lemma 2 intervals vs N0 with the 1 − δ line:
    rows A, B; columns (system, σ_w); one line per estimator / γ."""
    cols, meta = as_columns(records), spec_meta(spec)
    systems = systems_of(cols) or ["(none)"]
    sig = sigmas_of(cols) or [None]
    rows_ = [(system, mat) for system in systems for mat in ("A", "B")]
    fig, axes = new_figure(
        len(rows_),
        len(sig),
        (3.9 * len(sig) + 0.8, 2.6 * len(rows_) + 1.2),
        sharex=True,
        sharey=True,
    )
    series = [
        (est, g)
        for est, g in ([("ols", None)] if np.any(cols["estimator"] == "ols") else [])
        + [("svr", g) for g in gammas_of(cols)]
    ]
    level = 1 - meta.delta
    lows = [level]
    for r, (system, mat) in enumerate(rows_):
        for c, s in enumerate(sig):
            ax = axes[r, c]
            f = f"coverage_{mat}"
            ms = select(cols, system=system, sigma_w=s) if s is not None else np.zeros(cols.n, bool)
            if not cols.has(f, ms):
                no_data_panel(ax, no_data_reason(cols, ms, (f,), meta))
                continue
            for i, (est, g) in enumerate(series):
                m = ms & select(cols, estimator=est, gamma=g)
                x, _, y, _ = by_N(cols, m, cols[f], mean_of)
                ax.plot(x, y, color=f"C{i}", lw=1.3, marker="." if len(x) < 8 else None)
                if np.isfinite(y).any():
                    lows.append(float(np.nanmin(y)))
            ax.axhline(level, color="k", ls="--", lw=1)
            ax.set_title(f"{system}, σ_w={fmt_num(s)}: {mat}", fontsize=9)
            if c == 0:
                ax.set_ylabel(f"coverage of {mat}_ij intervals", fontsize=9)
            if r == len(rows_) - 1:
                n0_axis(ax, n0_ratio(cols, ms))
            ax.grid(alpha=0.3)
    axes[0, 0].set_ylim(min(lows) - 0.03, 1.01)
    handles = [legend_line(f"C{i}", "-", gamma_label(e, g)) for i, (e, g) in enumerate(series)]
    handles.append(legend_line("k", "--", f"1 − δ = {fmt_num(level)}"))
    figure_legend(fig, handles, ncol=len(handles))
    figure_title(
        fig,
        "Empirical coverage of the Lemma 2 entry intervals (mean share of entries "
        "inside, over reps)",
        experiment,
        meta,
    )
    return fig


def fig_certified(records, spec=None, *, experiment: str | None = "E4"):
    """Share of repetitions whose observer gain L is certified (g(L) < 1), and
    the share with ρ(A − LC) < 1 for the true A, vs N0 per γ."""
    cols, meta = as_columns(records), spec_meta(spec)
    systems = systems_of(cols) or ["(none)"]
    fig, axes = new_figure(1, len(systems), (5.6 * len(systems), 5), sharey=True)
    gs = gammas_of(cols)
    for c, system in enumerate(systems):
        ax = axes[0, c]
        ms = select(cols, system=system)
        if not cols.has("certified", ms):
            no_data_panel(ax, no_data_reason(cols, ms, ("certified", "g_L"), meta))
            continue
        rho = cols["rho_true"]
        stable = np.where(np.isfinite(rho), (rho < 1).astype(float), np.nan)
        for i, g in enumerate(gs):
            m = ms & select(cols, estimator="svr", gamma=g)
            x, _, y, _ = by_N(cols, m, cols["certified"], mean_of)
            ax.plot(x, y, color=f"C{i}", lw=1.4)
            if np.isfinite(rho[m]).any():
                x2, _, y2, _ = by_N(cols, m, stable, mean_of)
                ax.plot(x2, y2, color=f"C{i}", lw=0.9, ls="--", alpha=0.7)
        ax.set_ylim(-0.02, 1.02)
        label_panel(ax, "share of repetitions", system, n0_ratio(cols, ms))
    handles = [legend_line(f"C{i}", "-", f"γ={fmt_num(g)}") for i, g in enumerate(gs)]
    handles += [
        legend_line("0.2", "-", "certified: g(L) < 1 (Theorem 2 on the Lemma 2 box)"),
        legend_line("0.2", "--", "ρ(A − LC) < 1 for the true A"),
    ]
    figure_legend(fig, handles, ncol=3)
    figure_title(fig, "Share of certified observer gains vs sample length", experiment, meta)
    return fig


def fig_svr_ols_diff(records, spec=None, *, experiment: str | None = "E2"):
    """max_ij |Ã_svr − Ã_ols| on the same data (mean over reps) vs N0, per γ
    (color) and σ_w (line style): where SVR and OLS really differ."""
    cols, meta = as_columns(records), spec_meta(spec)
    systems = systems_of(cols) or ["(none)"]
    fig, axes = new_figure(1, len(systems), (5.8 * len(systems), 5.2), sharey=True)
    d = svr_ols_diff(cols)
    gs = gammas_of(cols)
    sig = sigmas_of(cols)
    styles = ["-", "--", ":", "-."]
    for c, system in enumerate(systems):
        ax = axes[0, c]
        ms = select(cols, system=system)
        if not np.isfinite(d[ms]).any():
            why = (
                "needs OLS and SVR estimates (A_hat) of the same repetitions"
                if cols.has("rmse_A", ms)
                else no_data_reason(cols, ms, ("A_hat",), meta)
            )
            no_data_panel(ax, why)
            continue
        for i, g in enumerate(gs):
            for j, s in enumerate(sig):
                m = ms & select(cols, estimator="svr", gamma=g, sigma_w=s)
                x, _, y, _ = by_N(cols, m, d, mean_of)
                if np.isfinite(y).any():
                    ax.plot(x, y, color=f"C{i}", ls=styles[j % 4], lw=1.3)
        ax.set_yscale("log")
        ax.minorticks_off()
        ylabel = "max_ij |Ã_SVR − Ã_OLS| (mean over reps)"
        label_panel(ax, ylabel, system, n0_ratio(cols, ms), grid="both")
    handles = [legend_line(f"C{i}", "-", f"γ={fmt_num(g)}") for i, g in enumerate(gs)]
    handles += [legend_line("0.2", styles[j % 4], f"σ_w={fmt_num(s)}") for j, s in enumerate(sig)]
    figure_legend(fig, handles, ncol=len(handles))
    figure_title(
        fig, "SVR minus OLS: largest entry difference of Ã on the same data", experiment, meta
    )
    return fig
