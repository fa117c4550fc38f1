"""The audit of the uncertainty sets (docs/uncertainty.md#in-the-service): per
bounds_method, how often the box covers the truth, how wide it is, and from
which N it certifies the paper's systems stable.

``sources`` maps a bounds_method to the report columns of one experiment run
with it (the paper preset: E2 for "paper", A1 for "self-normalized", A2 for
"bootstrap"). Every statistic is computed on the SVR cells at the table's
gamma (present in every source) and, separately, on OLS.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from ..array_types import Array
from ..paper import TABLE2_GAMMA
from ..spec import BOUNDS_METHODS
from .columns import (
    Columns,
    Meta,
    as_columns,
    fmt_num,
    gamma_label,
    n0_ratio,
    select,
    sigmas_of,
    spec_meta,
    systems_of,
)
from .derived import all_inside, first_stable_certified
from .plotting import (
    MERGED_NOTE,
    differences,
    figure_title,
    grid_legend,
    joined,
    label_panel,
    legend_line,
    merge_identical,
    new_figure,
    no_data_panel,
    note,
    overlap_text,
    panel_title,
    plot_merged,
    ref_line,
    series_handle,
    value_axis,
)
from .series import context, figure_series, series_lines
from .style import REFERENCE, series_style, size, styled

AUDIT_SERIES = (("svr", TABLE2_GAMMA), ("ols", None))


def audit_sources(
    experiments: dict[str, dict[str, Any]], cols: dict[str, Columns]
) -> dict[str, str]:
    """bounds_method -> the experiment that represents it (the first one with
    coverage data; for "paper" E2 is preferred, the grid A1 and A2 share)."""
    out: dict[str, str] = {}
    names = sorted(experiments, key=lambda n: (n != "E2", list(experiments).index(n)))
    for name in names:
        spec = experiments[name].get("spec")
        if spec is None or not cols[name].has("coverage_A"):
            continue
        method = spec_meta(spec).bounds_method
        out.setdefault(method, name)
    return {m: out[m] for m in BOUNDS_METHODS if m in out}


def _mean(v: Array) -> float | None:
    v = v[np.isfinite(v)]
    return float(np.mean(v)) if v.size else None


def audit_rows(sources: dict[str, Columns], delta: float) -> list[dict[str, Any]]:
    """One row per (method, system, sigma_w, estimator): per-entry coverage of A
    and B, simultaneous coverage (every entry of A and of B inside), mean r_A,
    r_B (largest radius) and the first N with stable_certified in >= half the
    repetitions (None: never in the grid); ``delta`` is recorded in each row."""
    rows = []
    for method, records in sources.items():
        cols = as_columns(records)
        simul = all_inside(cols)
        first = first_stable_certified(cols)
        for system in systems_of(cols):
            for s in sigmas_of(cols, select(cols, system=system)):
                for est, g in AUDIT_SERIES:
                    m = select(cols, system=system, sigma_w=s, estimator=est, gamma=g)
                    if not m.any():
                        continue
                    hit = first.get((system, s, est, g))
                    rows.append(
                        {
                            "method": method,
                            "system": system,
                            "sigma_w": s,
                            "estimator": est,
                            "gamma": g,
                            "records": int(m.sum()),
                            "coverage_A": _mean(cols["coverage_A"][m]),
                            "coverage_B": _mean(cols["coverage_B"][m]),
                            "simultaneous": _mean(simul[m]),
                            "r_A": _mean(cols["r_A"][m]),
                            "r_B": _mean(cols["r_B"][m]),
                            "first_N": None if hit is None else hit["N"],
                            "N_max": None if hit is None else hit["N_max"],
                            "delta": delta,
                        }
                    )
    return rows


def audit_markdown(rows: list[dict[str, Any]], delta: float) -> str:
    head = (
        "| method | system | σ_w | estimator | records | coverage A | coverage B | "
        f"all inside (vs 1 − δ = {fmt_num(1 - delta)}) | mean r_A | mean r_B | "
        "first N certified stable |\n|---|---|---|---|---|---|---|---|---|---|---|"
    )
    lines = [head]
    for r in rows:
        first = (
            "—"
            if r["N_max"] is None
            else (f"never (N ≤ {r['N_max']})" if r["first_N"] is None else str(r["first_N"]))
        )
        lines.append(
            f"| {r['method']} | {r['system']} | {fmt_num(r['sigma_w'])} | "
            f"{gamma_label(r['estimator'], r['gamma'])} | {r['records']} | "
            f"{fmt_num(r['coverage_A'], 3)} | {fmt_num(r['coverage_B'], 3)} | "
            f"{fmt_num(r['simultaneous'], 3)} | {fmt_num(r['r_A'], 3)} | "
            f"{fmt_num(r['r_B'], 3)} | {first} |"
        )
    return "\n".join(lines) + "\n"


def audit_findings(rows: list[dict[str, Any]], delta: float) -> list[str]:
    """Per method: where the simultaneous coverage falls below 1 - delta."""
    level = 1 - delta
    out = []
    for method in dict.fromkeys(r["method"] for r in rows):
        mine = [r for r in rows if r["method"] == method and r["simultaneous"] is not None]
        if not mine:
            continue
        below = [r for r in mine if r["simultaneous"] < level]
        worst = min(mine, key=lambda r: r["simultaneous"])
        status = "holds" if not below else "does not hold"
        where = (
            f"{worst['system']} σ_w={fmt_num(worst['sigma_w'])} "
            f"{gamma_label(worst['estimator'], worst['gamma'])}"
        )
        certified = [r for r in mine if r["first_N"] is not None]
        out.append(
            f"[{status}] {method}: all entries of A and B inside at once in at least "
            f"1 − δ = {fmt_num(level)} of the records in {len(mine) - len(below)} of "
            f"{len(mine)} (system, σ_w, estimator) groups; lowest {fmt_num(worst['simultaneous'], 3)} "
            f"({where}); mean r_A {fmt_num(_mean(np.array([r['r_A'] or np.nan for r in mine])), 3)}; "
            f"certified stable (half the repetitions) somewhere in the grid in "
            f"{len(certified)} of {len(mine)} groups."
        )
    return out


ESTIMATOR_LOOK = {"svr": ("-", True), "ols": ("--", False)}  # line style, filled markers


def _style(i: int, estimator: str) -> dict[str, Any]:
    """Method ``i``'s colour and marker; the estimator's line style and marker:
    SVR small and filled, on top of OLS's larger open one (both stay visible
    where the curves coincide)."""
    ls, filled = ESTIMATOR_LOOK.get(estimator, ("-.", True))
    st = series_style(i, line=False)
    if filled:
        st.update(ls=ls, markerfacecolor=st["color"], zorder=3)
    else:
        st.update(ls=ls, markerfacecolor="white", markersize=5.5, zorder=2)
    return st


def _text_panel(ax: Any, title: str, text: str) -> None:
    """A panel with nothing to plot: its title and one statement, no axes."""
    panel_title(ax, title)
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes)
    ax.set_axis_off()


def _bottom_note(ax: Any, text: str) -> None:
    """``text`` in the lower left corner, on a white box (the axis leaves room
    below the data for it)."""
    ax.text(
        0.03,
        0.04,
        text,
        ha="left",
        va="bottom",
        transform=ax.transAxes,
        zorder=5,
        bbox=dict(boxstyle="round,pad=0.25", fc="white", ec="0.75", lw=0.5),
    )


def _audit_lines(
    srcs: dict[str, Columns], meta: Meta
) -> tuple[dict[tuple[str, str, str], Any], list[str], float | None]:
    """(quantity, method, system) -> the FIGURE_SERIES lines of that source; the
    systems; the σ_w shown (1 if any source has it)."""
    rows = figure_series("fig_bounds_audit")
    systems: list[str] = []
    sig: set[float] = set()
    for c in srcs.values():
        systems += [s for s in systems_of(c) if s not in systems]
        sig |= set(sigmas_of(c))
    sw = 1.0 if 1.0 in sig else (min(sig) if sig else None)
    lines: dict[tuple[str, str, str], Any] = {}
    for m, c in srcs.items():
        ctx = context(c, meta, table=TABLE2_GAMMA, sigma_ref=sw)
        for system in systems:
            pm = select(c, system=system)
            for key in rows:
                lines[(key, m, system)] = series_lines(c, meta, rows[key], pm, ctx)
    return lines, systems or ["(none)"], sw


def _pairs(
    lines: dict[tuple[str, str, str], Any], key: str, methods: list[str], system: str
) -> list[tuple[str, str, Any]]:
    """(method, series name, Line) of ``methods`` in one panel, SVR before OLS."""
    return [
        (m, f"{m} {gamma_label(ln.key['estimator'], TABLE2_GAMMA)}", ln)
        for m in methods
        for ln in sorted(lines[(key, m, system)], key=lambda ln: ln.key["estimator"] != "svr")
    ]


def _merged_items(
    ax: Any,
    items: list[tuple[str, Array, Array]],
    styles: dict[str, dict[str, Any]],
    *,
    panel: str,
    quantity: str,
    merged: dict[Any, Any],
    system: str,
) -> Any:
    """Draw items with identical ones merged; remember which merged (for the note)."""
    for names, _ in merge_identical(items):
        if len(names) > 1:
            merged.setdefault((quantity, tuple(names)), []).append(system)
    return plot_merged(ax, items, styles, panel=panel, quantity=quantity)


@styled
def fig_bounds_audit(
    sources: Mapping[str, Columns | Iterable[dict[str, Any]]],
    delta: float,
    *,
    experiment: str | None = None,
    seed: object = "?",
) -> Any:
    """Share of records with every entry of A and of B inside the box (linear, with
    the 1 − δ line) and mean r_A (log) against N0, columns the systems at σ_w = 1.
    One colour and marker per bounds_method; SVR at the table's γ solid with filled
    markers, OLS dashed with open markers. A method whose share is 1 at every N0
    of a system is a caption note there, not a flat line; identical curves are
    drawn once (docs/uncertainty.md#in-the-service)."""
    srcs = {m: as_columns(c) for m, c in sources.items()}
    meta = Meta(delta=delta, seed=seed)
    level = 1 - delta
    lines, systems, sw = _audit_lines(srcs, meta)
    order = {m: i for i, m in enumerate(srcs)}
    ones: dict[str, list[str]] = {}  # method -> systems where every record is inside
    for (key, m, system), ls in lines.items():
        if key == "all_inside" and ls and all(np.all(ln.y[np.isfinite(ln.y)] == 1) for ln in ls):
            ones.setdefault(m, []).append(system)

    def cover_pairs(system: str) -> list[tuple[str, str, Any]]:
        drawn = [m for m in srcs if system not in ones.get(m, [])]
        return _pairs(lines, "all_inside", drawn, system)

    with_cover = any(cover_pairs(s) for s in systems)
    nr = 2 if with_cover else 1
    fig, axes = new_figure(nr, len(systems), size("two", 12.5 if with_cover else 7.5), sharex=True)
    styles: dict[str, dict[str, Any]] = {}

    def items_of(pairs: list[tuple[str, str, Any]]) -> list[tuple[str, Array, Array]]:
        for m, name, ln in pairs:
            styles.setdefault(name, _style(order[m], ln.key["estimator"]))
        return [(name, ln.x, ln.y) for _, name, ln in pairs]

    ratio = next((n0_ratio(c) for c in srcs.values() if c.n), None)
    merged: dict[Any, Any] = {}
    title_sw = f"σ_w={fmt_num(sw)}"
    lows, counts, corner = [level], [], []
    for c, system in enumerate(systems):
        top = f"{system}, {title_sw}"
        if with_cover:
            ax = axes[0, c]
            pairs = cover_pairs(system)
            if not pairs:
                _text_panel(
                    ax, top, "every entry of A and of B inside\nin every record, every method"
                )
            else:
                items = items_of(pairs)
                _merged_items(
                    ax,
                    items,
                    styles,
                    panel=f"{system}: all inside",
                    quantity="all_inside",
                    merged=merged,
                    system=system,
                )
                ref_line(ax, level, ls=":", lw=1.0)
                lows += [float(np.nanmin(ln.y)) for *_, ln in pairs]
                counts += [int(k) for *_, ln in pairs for k in ln.count]
                label_panel(ax, "share with all entries inside", top, None, xlabel=False)
                full = [m for m in srcs if system in ones.get(m, [])]
                if full:
                    corner.append((ax, f"{joined(full)}: all inside\nat every N0 (not drawn)"))
        ax = axes[nr - 1, c]
        pairs = _pairs(lines, "r_A", list(srcs), system)
        if not pairs:
            no_data_panel(ax, f"no r_A at {title_sw}")
            continue
        _merged_items(
            ax,
            items_of(pairs),
            styles,
            panel=f"{system}: r_A",
            quantity="r_A",
            merged=merged,
            system=system,
        )
        value_axis(ax)
        label_panel(ax, "mean r_A (largest radius)", None if with_cover else top, ratio)
    if with_cover:
        lo = min(lows)
        pad = 0.06 * (1 - lo) + 0.003
        below = 0.4 * (1 - lo) + 0.004 if corner else pad  # room for the notes under the data
        for c in range(len(systems)):
            axes[0, c].set_ylim(lo - below, 1 + pad)
        for ax, text in corner:
            _bottom_note(ax, text)
    _audit_notes(fig, srcs, lines, systems, ones, merged, counts, level, title_sw)
    method_handles = [
        series_handle(m, _style(order[m], "svr"))
        for m in srcs
        if any(n.startswith(m + " ") for n in styles)
    ]
    kinds = [
        legend_line(ls=ESTIMATOR_LOOK[e][0], label=lab)
        for e, lab in (
            ("svr", f"{gamma_label('svr', TABLE2_GAMMA)} (solid, filled markers)"),
            ("ols", "OLS (dashed, large open markers)"),
        )
        if any(st["ls"] == ESTIMATOR_LOOK[e][0] for st in styles.values())
    ]
    if with_cover:
        kinds.append(legend_line(REFERENCE, ":", f"1 − δ = {fmt_num(level)}", lw=1.0))
    grid_legend(fig, [method_handles, kinds])
    figure_title(
        fig,
        "Uncertainty sets: share of records with every entry inside, and radius, per bounds_method",
        experiment,
        meta,
    )
    return fig


def _audit_notes(
    fig: Any,
    srcs: dict[str, Columns],
    lines: dict[tuple[str, str, str], Any],
    systems: list[str],
    ones: dict[str, Any],
    merged: dict[Any, Any],
    counts: list[Any],
    level: float,
    title_sw: str,
) -> None:
    """Caption notes: shares of 1 not drawn, identical curves, SVR ≈ OLS radii,
    how many records each share counts."""
    by_where: dict[tuple[Any, ...], list[str]] = {}
    for m, where in ones.items():
        by_where.setdefault(tuple(where), []).append(m)
    for where, methods in by_where.items():
        n = sum(
            int(ln.count.sum())
            for m in methods
            for s in where
            for ln in lines[("all_inside", m, s)]
        )
        note(
            fig,
            f"The {joined(methods)} box{'es contain' if len(methods) > 1 else ' contains'} "
            f"every entry of A and of B in all {n:,} records at {title_sw} on "
            f"{joined(list(where))} (every N0, SVR γ={fmt_num(TABLE2_GAMMA)} and OLS), above "
            f"1 − δ = {fmt_num(level)}: a share of 1 everywhere, not drawn.",
        )
    if merged:
        what = {"all_inside": "all-inside shares", "r_A": "r_A curves"}
        parts = [
            f"the {what[q]} of {joined(list(names))} on {joined(sorted(set(where)))}"
            for (q, names), where in merged.items()
        ]
        note(fig, f"Identical (within 1e-12): {'; '.join(parts)}. " + MERGED_NOTE)
    for m in srcs:
        rels = []
        for s in systems:
            by = {ln.key["estimator"]: ln for ln in lines[("r_A", m, s)]}
            if "svr" in by and "ols" in by:
                _, big = differences(
                    [("svr", by["svr"].x, by["svr"].y)], ("ols", by["ols"].x, by["ols"].y)
                )
                rels.append(big[3])
        if rels and 0 < max(rels) < 0.03:
            note(
                fig,
                overlap_text(
                    f"The {m} r_A curves of {gamma_label('svr', TABLE2_GAMMA)} and OLS",
                    max(rels),
                    "OLS",
                )
                + ".",
            )
    if counts:
        k = min(counts)
        note(
            fig,
            f"Each share counts {k if k == max(counts) else f'{k} to {max(counts)}'} records "
            f"(one record outside lowers it by {fmt_num(1 / k, 2)}); a box that covers with "
            f"probability exactly 1 − δ has at least one of {k} outside with probability "
            f"{100 * (1 - level**k):.0f} %.",
        )
