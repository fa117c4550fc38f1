"""The audit of the uncertainty sets (issue 12, SPEC section 3.1): per
bounds_method, how often the box covers the truth, how wide it is, and from
which N it certifies the paper's systems stable.

``sources`` maps a bounds_method to the report columns of one experiment run
with it (the paper preset: E2 for "paper", A1 for "self-normalized", A2 for
"bootstrap"). Every statistic is computed on the SVR cells at the table's
gamma (present in every source) and, separately, on OLS.
"""

from __future__ import annotations

import numpy as np

from ..paper import TABLE2_GAMMA
from ..spec import BOUNDS_METHODS
from .columns import (
    Columns,
    Meta,
    as_columns,
    by_N,
    fmt_num,
    gamma_label,
    mean_of,
    n0_ratio,
    select,
    sigmas_of,
    spec_meta,
    systems_of,
)
from .derived import first_stable_certified
from .plotting import (
    figure_legend,
    figure_title,
    label_panel,
    legend_line,
    new_figure,
    no_data_panel,
)

AUDIT_SERIES = (("svr", TABLE2_GAMMA), ("ols", None))


def audit_sources(experiments: dict[str, dict], cols: dict[str, Columns]) -> dict[str, str]:
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


def _simultaneous(cols: Columns) -> np.ndarray:
    """1 where every entry of A and of B is inside, 0 where not, NaN where undefined."""
    a, b = cols["coverage_A"], cols["coverage_B"]
    ok = np.isfinite(a) & np.isfinite(b)
    return np.where(ok, ((a == 1) & (b == 1)).astype(float), np.nan)


def _mean(v: np.ndarray) -> float | None:
    v = v[np.isfinite(v)]
    return float(np.mean(v)) if v.size else None


def audit_rows(sources: dict[str, Columns], delta: float) -> list[dict]:
    """One row per (method, system, sigma_w, estimator): per-entry coverage of A
    and B, simultaneous coverage (every entry of A and of B inside), mean r_A,
    r_B (largest radius) and the first N with stable_certified in >= half the
    repetitions (None: never in the grid); ``delta`` is recorded in each row."""
    rows = []
    for method, records in sources.items():
        cols = as_columns(records)
        simul = _simultaneous(cols)
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


def audit_markdown(rows: list[dict], delta: float) -> str:
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


def audit_findings(rows: list[dict], delta: float) -> list[str]:
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


def fig_bounds_audit(
    sources: dict[str, Columns], delta: float, *, experiment: str | None = None, seed="?"
):
    """Simultaneous coverage and mean r_A against N0, one line per method (SVR at
    the table's gamma, solid; OLS, dashed): columns are the systems at sigma_w = 1."""
    srcs = {m: as_columns(c) for m, c in sources.items()}
    systems = []
    for c in srcs.values():
        systems += [s for s in systems_of(c) if s not in systems]
    systems = systems or ["(none)"]
    fig, axes = new_figure(2, len(systems), (4.2 * len(systems) + 0.8, 6.2), sharex=True)
    level = 1 - delta
    lows = [level]
    for col, system in enumerate(systems):
        for row, what in enumerate(("simultaneous", "r_A")):
            ax = axes[row, col]
            drawn = False
            ratio = None
            for i, cols in enumerate(srcs.values()):
                values = _simultaneous(cols) if what == "simultaneous" else cols["r_A"]
                for (est, g), ls in zip(AUDIT_SERIES, ("-", "--")):
                    m = select(cols, system=system, sigma_w=1.0, estimator=est, gamma=g)
                    x, _, y, _ = by_N(cols, m, values, mean_of)
                    if x.size and np.isfinite(y).any():
                        ax.plot(
                            x, y, color=f"C{i}", ls=ls, lw=1.3, marker="." if x.size < 8 else None
                        )
                        drawn = True
                        ratio = ratio or n0_ratio(cols, m)
                        if what == "simultaneous":
                            lows.append(float(np.nanmin(y)))
            if not drawn:
                no_data_panel(ax, "no records at σ_w = 1")
                continue
            if what == "simultaneous":
                ax.axhline(level, color="k", ls=":", lw=1)
                label_panel(
                    ax, "share with all entries inside", f"{system}, σ_w=1", None, xlabel=False
                )
            else:
                ax.set_yscale("log")
                label_panel(ax, "mean r_A (largest radius)", f"{system}, σ_w=1", ratio)
    for col in range(len(systems)):
        axes[0, col].set_ylim(min(lows) - 0.03, 1.01)
    handles = [legend_line(f"C{i}", "-", m) for i, m in enumerate(srcs)]
    handles += [
        legend_line("0.4", "-", gamma_label(*AUDIT_SERIES[0])),
        legend_line("0.4", "--", gamma_label(*AUDIT_SERIES[1])),
        legend_line("k", ":", f"1 − δ = {fmt_num(level)}"),
    ]
    figure_legend(fig, handles, ncol=len(handles))
    figure_title(
        fig,
        "Uncertainty sets: simultaneous coverage and radius per bounds_method",
        experiment,
        Meta(delta=delta, seed=seed),
    )
    return fig
