"""Findings: statements generated from the records on where the paper's claims
hold here and where not, with counts (docs/science.md sections 3-7 and
#93-what-the-reproduction-shows)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from ..norms import schur_stable, spectral_radius, stability_radius
from ..paper import PUBLISHED_CLAIMS
from ..records import GROUP_FIELDS
from .columns import (
    STAGE_FIELDS,
    Columns,
    Meta,
    as_columns,
    by_N,
    fmt_num,
    gamma_label,
    gammas_of,
    group_indices,
    select,
    sigmas_of,
    spec_meta,
    systems_of,
)
from .derived import first_stable_certified, svr_ols_diff
from .tables import mean_over_reps_then_N


def _pct(k: int, n: int) -> str:
    return f"{k} of {n} ({100.0 * k / n:.1f} %)" if n else f"{k} of 0"


def _stage_findings(cols: Columns, meta: Meta) -> list[str]:
    out = []
    for stage in meta.stages:
        fs = STAGE_FIELDS.get(stage, ())
        if fs and not any(cols.has(f) for f in fs):
            notes = [v for v in cols["notes"] if v]
            extra = f' Notes on the records: "{notes[0][:120]}".' if notes else ""
            out.append(
                f"[no data] Stage '{stage}' is in the spec but its fields "
                f"({', '.join(fs)}) are null in all {cols.n} records.{extra}"
            )
    return out


def _f_svr_vs_ols(cols: Columns) -> list[str]:
    out: list[str] = []
    if not (
        cols.has("rmse_A")
        and np.any(cols["estimator"] == "ols")
        and np.any(cols["estimator"] == "svr")
    ):
        return out
    claim = PUBLISHED_CLAIMS["svr_beats_ols_large_noise"]
    gs = gammas_of(cols)
    wins = 0
    cells = 0
    max_rel = 0.0
    for system in systems_of(cols):
        for s in sigmas_of(cols, select(cols, system=system)):
            parts = []
            for mat in ("A", "B"):
                f = f"rmse_{mat}"
                base, _, _ = mean_over_reps_then_N(
                    cols, select(cols, system=system, estimator="ols", sigma_w=s), f
                )
                if base is None:
                    continue
                better = []
                for g in gs:
                    v, _, _ = mean_over_reps_then_N(
                        cols, select(cols, system=system, estimator="svr", gamma=g, sigma_w=s), f
                    )
                    if v is None:
                        continue
                    cells += 1
                    max_rel = max(max_rel, abs(v - base) / base if base else 0.0)
                    if v < base:
                        better.append(g)
                        wins += 1
                parts.append(
                    f"{mat}: {len(better)} of {len(gs)} γ"
                    + (f" ({', '.join(fmt_num(g) for g in better)})" if better else "")
                )
            out.append(
                f"[info] SVR beats OLS in mean RMSE for {system}, σ_w={fmt_num(s)}: "
                + "; ".join(parts)
                + "."
            )
    # the paper's claim, at the largest noise level
    top = max(sigmas_of(cols))
    k = n = 0
    for system in systems_of(cols):
        for mat in ("A", "B"):
            f = f"rmse_{mat}"
            base, _, _ = mean_over_reps_then_N(
                cols, select(cols, system=system, estimator="ols", sigma_w=top), f
            )
            for g in gs:
                v, _, _ = mean_over_reps_then_N(
                    cols, select(cols, system=system, estimator="svr", gamma=g, sigma_w=top), f
                )
                if base is not None and v is not None:
                    n += 1
                    k += v < base
    status = "holds" if n and k == n else ("does not hold" if k == 0 else "partly")
    out.insert(
        0,
        (
            f'[{status}] Paper ({claim["where"]}): "{claim["quote"]}". Here, at σ_w={fmt_num(top)}, '
            f"SVR has the lower mean RMSE in {_pct(k, n)} (system, matrix, γ) cells; over all "
            f"{cells} cells SVR wins {wins}. The largest relative RMSE difference between SVR and "
            f"OLS anywhere is {100 * max_rel:.3g} %."
        ),
    )
    return out


def _f_coverage(cols: Columns, meta: Meta) -> list[str]:
    if meta.bounds_method != "paper":
        return _f_box_coverage(cols, meta)
    out = []
    level = 1 - meta.delta
    claim = PUBLISHED_CLAIMS["lemma2_intervals"]
    for mat in ("A", "B"):
        f = f"coverage_{mat}"
        if not cols.has(f):
            continue
        groups = group_indices(cols, GROUP_FIELDS, np.isfinite(cols[f]))
        below = []
        for key, idx in groups.items():
            mcov = float(np.mean(cols[f][idx]))
            if mcov < level:
                below.append((mcov, key))
        rec_miss = int(np.sum(cols[f][np.isfinite(cols[f])] < 1))
        n_rec = int(np.isfinite(cols[f]).sum())
        status = "holds" if not below else "does not hold"
        text = (
            f"[{status}] Lemma 2 intervals for {mat} (paper, {claim['where']}: "
            f'"{claim["quote"]}"): mean empirical coverage is below 1 − δ = {fmt_num(level)} '
            f"in {_pct(len(below), len(groups))} groups (system, σ_w, N, estimator, γ); "
            f"{_pct(rec_miss, n_rec)} records have at least one entry of {mat} outside "
            f"its interval."
        )
        if below:
            below.sort(key=lambda t: t[0])
            worst = ", ".join(
                f"{k[0]} σ_w={fmt_num(k[1])} N={fmt_num(k[2])} {gamma_label(k[3], k[4])}: {fmt_num(c, 3)}"
                for c, k in below[:3]
            )
            text += f" Lowest: {worst}."
        out.append(text)
    return out


def _f_box_coverage(cols: Columns, meta: Meta) -> list[str]:
    """A sound method's box (docs/uncertainty.md) must hold for every entry of A and
    of B at once with probability >= 1 - delta: check that share per group."""
    level = 1 - meta.delta
    ok = np.isfinite(cols["coverage_A"]) & np.isfinite(cols["coverage_B"])
    if not ok.any():
        return []
    inside = (cols["coverage_A"] == 1) & (cols["coverage_B"] == 1)
    groups = group_indices(cols, GROUP_FIELDS, ok)
    below = sorted(
        (float(np.mean(inside[idx])), key)
        for key, idx in groups.items()
        if np.mean(inside[idx]) < level
    )
    status = "holds" if not below else "does not hold"
    claim = (
        "claimed"
        if meta.bounds_method == "self-normalized"
        else "targeted, approximately: no finite-sample guarantee"
    )
    text = (
        f"[{status}] The {meta.bounds_method} box (every entry of A and of B inside at "
        f"once, probability ≥ 1 − δ = {fmt_num(level)} {claim}): the share of repetitions "
        f"covered is below 1 − δ in {_pct(len(below), len(groups))} groups (system, σ_w, N, "
        f"estimator, γ); overall {_pct(int(inside[ok].sum()), int(ok.sum()))} records covered."
    )
    if below:
        worst = ", ".join(
            f"{k[0]} σ_w={fmt_num(k[1])} N={fmt_num(k[2])} {gamma_label(k[3], k[4])}: "
            f"{fmt_num(c, 3)}"
            for c, k in below[:3]
        )
        text += f" Lowest: {worst}."
    return [text]


def _f_theorem1(cols: Columns, meta: Meta) -> list[str]:
    out = []
    for mat in ("A", "B"):
        f = f"thm1_holds_{mat}"
        v = cols[f]
        ok = np.isfinite(v)
        n = int(ok.sum())
        if not n:
            continue
        k = int(np.sum(v[ok] == 0))
        rate = k / n
        status = "holds" if k == 0 else ("partly" if rate <= meta.delta else "does not hold")
        per = []
        for (est, g), idx in group_indices(cols, ("estimator", "gamma"), ok).items():
            kk = int(np.sum(v[idx] == 0))
            per.append(f"{gamma_label(est, g)}: {kk}/{idx.size}")
        out.append(
            f"[{status}] Theorem 1 for {mat} (every row): violated in {_pct(k, n)} "
            f"records (the theorem allows probability δ = {fmt_num(meta.delta)}). "
            f"By estimator: {'; '.join(per)}."
        )
    return out


def _f_stable_certified(cols: Columns, meta: Meta) -> list[str]:
    out: list[str] = []
    if not cols.has("stable_certified"):
        return out
    claim = PUBLISHED_CLAIMS["stable_after_sample_length"]
    box_name = (
        "of the paper's bounds (docs/science.md#35-stability-certificate-of-a)"
        if meta.bounds_method == "paper"
        else f"on the {meta.bounds_method} box (docs/uncertainty.md)"
    )
    first = first_stable_certified(cols)
    by_sys: dict[str, list[str]] = {}
    never: dict[str, list[str]] = {}
    n_max: dict[str, int] = {}
    earliest = None
    for (system, s, est, g), hit in first.items():
        label = f"σ_w={fmt_num(s)} {gamma_label(est, g)}"
        by_sys.setdefault(system, [])
        n_max[system] = max(n_max.get(system, 0), hit["N_max"])
        if hit["N0"] is None:
            never.setdefault(system, []).append(label)
        else:
            by_sys[system].append(f"{label}: N={hit['N']} (N0={hit['N0']})")
            if system == claim["system"]:
                earliest = hit["N0"] if earliest is None else min(earliest, hit["N0"])
    for system, parts in by_sys.items():
        nv = never.get(system, [])
        total = len(parts) + len(nv)
        text = (
            f"[info] First N at which stable_certified (ρ upper bound < 1) holds in ≥ half "
            f"the repetitions, {system}: "
        )
        if parts:
            text += "; ".join(parts) + ". "
        if nv:
            which = "all" if not parts else f"{len(nv)} of {total}"
            text += (
                f"Never in the grid (N ≤ {n_max[system]}) for {which} (σ_w, estimator) "
                f"combinations" + (f": {', '.join(nv)}." if parts else ".")
            )
        out.append(text.strip())
    if claim["system"] in by_sys:
        pub = claim["sample_length"]
        n0_max = max(h["N0_max"] for k, h in first.items() if k[0] == claim["system"])
        if earliest is not None and earliest <= pub:
            status = "holds"
        elif earliest is None and n0_max < pub:
            status = "no data"  # the grid stops before the paper's sample length
        else:
            status = "does not hold"
        got = (
            f"never in the grid (N0 ≤ {n0_max})"
            if earliest is None
            else f"from N0={earliest} at the earliest"
        )
        out.insert(
            0,
            f'[{status}] Paper ({claim["where"]}, published): "{claim["quote"]}" '
            f"(sample length {pub}). Here, with the sound Perron-Frobenius certificate "
            f"{box_name}, {claim['system']} is certified stable {got}.",
        )
    # soundness: a certificate of stability for a truly unstable A is a false positive
    sc = cols["stable_certified"]
    for system in systems_of(cols):
        truth = meta.truth.get(system)
        if truth is None:
            continue
        rho = float(spectral_radius(truth[0]))
        if not schur_stable(
            stability_radius(truth[0])
        ):  # unstable by the one rule of the certificates
            m = select(cols, system=system) & np.isfinite(sc)
            k = int(np.sum(sc[m] == 1))
            status = "holds" if k == 0 else "does not hold"
            out.append(
                f"[{status}] Soundness on {system} (true ρ(A) = {fmt_num(rho)}): "
                f"stable_certified is true in {_pct(k, int(m.sum()))} records."
            )
    return out


def _f_cost(cols: Columns, meta: Meta) -> list[str]:
    out = []
    dJ = cols["delta_J"]
    if cols.has("delta_J"):
        claim = PUBLISHED_CLAIMS["delta_j_positive"]
        for system in systems_of(cols):
            ms = select(cols, system=system) & np.isfinite(dJ)
            if not ms.any():
                continue
            n = int(ms.sum())
            k = int(np.sum(dJ[ms] < 0))
            per = []
            neg_groups = 0
            groups = group_indices(cols, ("gamma", "N"), ms)
            for g in gammas_of(cols, ms):
                m = ms & select(cols, gamma=g)
                per.append(f"γ={fmt_num(g)}: {int(np.sum(dJ[m] < 0))}/{int(m.sum())}")
            for idx in groups.values():
                neg_groups += float(np.mean(dJ[idx])) < 0
            status = "holds" if k == 0 else ("does not hold" if neg_groups else "partly")
            out.append(
                f'[{status}] Paper ({claim["where"]}): "{claim["quote"]}". On {system}, '
                f"ΔJ = J_b − J < 0 in {_pct(k, n)} cells ({'; '.join(per)}); the mean ΔJ "
                f"over repetitions is negative in {_pct(neg_groups, len(groups))} "
                f"(γ, N) groups."
            )
    J = cols["J_exact"]
    if cols.has("J_exact"):
        claim = PUBLISHED_CLAIMS["cost_variance_small_gamma"]
        for system in systems_of(cols):
            ms = select(cols, system=system) & np.isfinite(J)
            gs = gammas_of(cols, ms)
            if len(gs) < 2:
                continue
            stds = []
            for g in gs:
                m = ms & select(cols, gamma=g)
                _, _, sd, _ = by_N(cols, m, J, lambda v: float(np.std(v)))
                stds.append(float(np.nanmean(sd)) if np.isfinite(sd).any() else np.nan)
            dec = all(a > b for a, b in zip(stds, stds[1:]))
            ratio = stds[0] / stds[-1] if stds[-1] else float("nan")
            # "much larger": decreasing in gamma and at least twice as large at the
            # smallest gamma as at the largest; "partly" if only larger
            if dec and ratio >= 2:
                status = "holds"
            elif ratio > 1:
                status = "partly"
            else:
                status = "does not hold"
            out.append(
                f'[{status}] Paper ({claim["where"]}): "{claim["quote"]}". On {system}, '
                f"the standard deviation of J over repetitions (mean over N) is "
                + ", ".join(f"γ={fmt_num(g)}: {fmt_num(v, 3)}" for g, v in zip(gs, stds))
                + f"; smallest-γ / largest-γ ratio {fmt_num(ratio, 3)} (counted as holding "
                f"when decreasing in γ with a ratio of at least 2)."
            )
    mc, se = cols["J_mc"], cols["J_mc_se"]
    ok = np.isfinite(mc) & np.isfinite(se) & np.isfinite(J)
    if ok.any():
        bad = int(np.sum(np.abs(mc[ok] - J[ok]) > 4 * se[ok]))
        status = "holds" if bad == 0 else "does not hold"
        out.append(
            f"[{status}] Monte Carlo J agrees with the exact finite-horizon J within "
            f"4 standard errors in {_pct(int(ok.sum()) - bad, int(ok.sum()))} records "
            f"that have a Monte Carlo estimate."
        )
    if cols.has("certified"):
        cert = cols["certified"]
        for system in systems_of(cols):
            ms = select(cols, system=system) & np.isfinite(cert)
            if not ms.any():
                continue
            per = []
            for g in gammas_of(cols, ms):
                m = ms & select(cols, gamma=g)
                per.append(f"γ={fmt_num(g)}: {_pct(int(np.sum(cert[m] == 1)), int(m.sum()))}")
            rho = cols["rho_true"]
            mm = ms & (cert == 1) & np.isfinite(rho)
            unsound = int(np.sum(~schur_stable(rho[mm])))
            if not mm.any():
                status, tail = "info", "No certified gain, so their soundness is not tested here."
            else:
                status = "holds" if unsound == 0 else "does not hold"
                tail = (
                    f"Certified gains with ρ(A − LC) ≥ 1 − 10⁻¹⁰ for the true A: "
                    f"{_pct(unsound, int(mm.sum()))}."
                )
            out.append(
                f"[{status}] Certified gains (g(L) < 1) on {system}: "
                + "; ".join(per)
                + ". "
                + tail
            )
    return out


def _f_svr_ols_diff(cols: Columns) -> list[str]:
    d = svr_ols_diff(cols)
    if not np.isfinite(d).any():
        return []
    parts = []
    for g in gammas_of(cols):
        m = select(cols, estimator="svr", gamma=g) & np.isfinite(d)
        if m.any():
            parts.append(
                f"γ={fmt_num(g)}: max {fmt_num(float(d[m].max()), 3)}, "
                f"median {fmt_num(float(np.median(d[m])), 3)}"
            )
    return [
        "[info] SVR and OLS estimates of A on the same data differ by at most (largest "
        "entry difference over all records): " + "; ".join(parts) + "."
    ]


def _f_notes(cols: Columns) -> list[str]:
    codes, values = cols.codes("notes")
    per_value = np.bincount(codes, minlength=len(values)).tolist()
    n_notes = sum(c for v, c in zip(values, per_value) if v)
    if not n_notes:
        return []
    counts: dict[str, int] = {}
    for v, c in zip(values, per_value):
        if not v:
            continue
        for part in str(v).split("; "):
            counts[part] = counts.get(part, 0) + c
    notes = range(n_notes)
    top = sorted(counts.items(), key=lambda kv: -kv[1])[:4]
    return [
        f"[info] {_pct(len(notes), cols.n)} records carry notes (null fields and why): "
        + "; ".join(f'"{k[:100]}" ×{v}' for k, v in top)
        + "."
    ]


FINDING_TOPICS = ("estimate", "bounds", "cost", "notes")


def findings(
    records: Columns | Iterable[dict[str, Any]],
    spec: Any = None,
    *,
    topics: Iterable[str] = FINDING_TOPICS,
) -> list[str]:
    """Statements generated from the data: where the paper's claims hold here and
    where not, with counts. Each starts with [holds], [does not hold], [partly],
    [no data] or [info]. ``topics``: the subset of FINDING_TOPICS to report
    (e.g. only "bounds" for a run that repeats another's data with another
    bounds_method)."""
    cols, meta = as_columns(records), spec_meta(spec)
    if cols.n == 0:
        return ["[no data] No records."]
    out: list[str] = []
    out += _stage_findings(cols, meta)
    if "estimate" in topics:
        out += _f_svr_vs_ols(cols)
    if "bounds" in topics:
        out += _f_coverage(cols, meta)
        out += _f_theorem1(cols, meta)
        out += _f_stable_certified(cols, meta)
    if "cost" in topics:
        out += _f_cost(cols, meta)
    if "estimate" in topics:
        out += _f_svr_ols_diff(cols)
    if "notes" in topics:
        out += _f_notes(cols)
    return out
