"""Report: Table 2, figures, findings and `reproduce` on the reduced grid.

Table values are checked against an independent plain-Python computation from
the written records.jsonl; findings counts against hand counts on constructed
records (the cost stages are exercised with constructed records, so these
tests do not depend on the observer pipeline being available).
"""

import csv
import io
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from svrobs_cli import reproduce as rep_mod
from svrobs_cli import reproduce_plan
from svrobs_core import RECORD_FIELDS, parse_spec, run_spec
from svrobs_core import report as rpt
from svrobs_core.paper import PUBLISHED_TABLE2, paper_specs
from svrobs_core.records import empty_record
from svrobs_core.report import table2

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
FIGURES = (
    "fig_rmse",
    "fig2",
    "fig3",
    "fig4",
    "fig5",
    "fig_coverage",
    "fig_certified",
    "fig_svr_ols_diff",
    "fig_bounds_audit",
)


# ---------------------------------------------------------------------------
# constructed records
# ---------------------------------------------------------------------------


def make_records(spec_obj, seed=0, cost=True):
    """Section 10 records with every field filled from a seeded generator."""
    spec = parse_spec(spec_obj)
    rng = np.random.default_rng(seed)
    recs = []
    for si, system in enumerate(spec.systems):
        for wi, sw in enumerate(spec.sigma_w):
            for N in spec.N:
                for rep in range(spec.reps):
                    base = rng.normal(0, 0.02, system.A.shape)
                    baseB = rng.normal(0, 0.05, system.B.shape)
                    for est in spec.estimators:
                        for g in [None] if est == "ols" else list(spec.gamma):
                            shrink = 1.0 / (1.0 + (g or 0.0) / N)
                            A_hat = (system.A + base) * shrink
                            B_hat = (system.B + baseB) * shrink
                            r = empty_record()
                            r.update(
                                system=system.name,
                                sigma_w=sw,
                                N=N,
                                N0=(spec.T0 - 1) * N,
                                estimator=est,
                                gamma=g,
                                rep=rep,
                                seed_key=[si, wi, N, rep],
                                A_hat=A_hat.tolist(),
                                B_hat=B_hat.tolist(),
                                rmse_A=float(np.sqrt(np.mean((A_hat - system.A) ** 2))),
                                rmse_B=float(np.sqrt(np.mean((B_hat - system.B) ** 2))),
                                H_A=0.1,
                                H_B=0.2,
                                r_A=0.3 / math.sqrt(N),
                                r_B=0.6 / math.sqrt(N),
                                eps_A=1.0 / math.sqrt(N),
                                eps_B=2.0 / math.sqrt(N),
                                coverage_A=1.0,
                                coverage_B=1.0,
                                thm1_holds_A=True,
                                thm1_holds_B=True,
                                rho_upper_bound=2.0 - N / 100.0,
                                stable_certified=(2.0 - N / 100.0) < 1,
                            )
                            if cost and spec.has("gain"):
                                J = 3.0 + rng.exponential(1.0 / (1 + 100 * (g or 0)))
                                r.update(
                                    g_L=0.9,
                                    certified=bool(rng.random() < 0.7),
                                    rho_true=0.8,
                                    J_exact=J,
                                    J_star=3.0,
                                    J_bound=J + rng.normal(0.5, 0.5),
                                    J_mc=None,
                                    J_mc_se=None,
                                )
                                r["delta_J"] = r["J_bound"] - J
                                if spec.mc_reps is None or rep < spec.mc_reps:
                                    r["J_mc"], r["J_mc_se"] = J + 0.01, 0.05
                            recs.append(r)
    # cost_ratio per record against gamma_ref of the same repetition
    ref = {}
    for r in recs:
        if r["J_exact"] is not None and r["gamma"] == spec.gamma_ref:
            ref[(r["system"], r["sigma_w"], r["N"], r["rep"])] = r["J_exact"]
    for r in recs:
        j = ref.get((r["system"], r["sigma_w"], r["N"], r["rep"]))
        if j is not None and r["J_exact"] is not None:
            r["cost_ratio"] = abs(r["J_exact"] - j) / j
    return recs


def tiny_spec(**kw):
    s = {
        "systems": ["paper-stable", "paper-unstable"],
        "sigma_w": [0.1, 10.0],
        "N": [10, 20, 30],
        "gamma": [0.01, 0.1],
        "reps": 4,
        "estimators": ["ols", "svr"],
    }
    s.update(kw)
    return s


# ---------------------------------------------------------------------------
# Table 2
# ---------------------------------------------------------------------------


def independent_table(records, gamma=0.05):
    """Plain Python: mean of rmse over every (N, rep) record per cell (balanced grid)."""
    acc = {}
    for r in records:
        if r["estimator"] == "ols":
            col = "ols"
        elif r["estimator"] == "svr" and r["gamma"] is not None and abs(r["gamma"] - gamma) < 1e-12:
            col = "svr"
        else:
            continue
        for mat in ("A", "B"):
            key = (r["system"], float(r["sigma_w"]), mat, col)
            s, n = acc.get(key, (0.0, 0))
            acc[key] = (s + r[f"rmse_{mat}"], n + 1)
    return {k: s / n for k, (s, n) in acc.items()}


def test_table2_on_constructed_records():
    recs = make_records(tiny_spec(gamma=[0.05, 0.1]), seed=3, cost=False)
    rows = rpt.table2(recs)
    ind = independent_table(recs)
    assert len(rows) == 2 * 2 * 2
    for row in rows:
        for col in ("ols", "svr"):
            want = ind[(row["system"], row["sigma_w"], row["matrix"], col)]
            assert row[col] == pytest.approx(want, rel=1e-12)
        pub = PUBLISHED_TABLE2.get((row["system"], row["sigma_w"], row["matrix"]))
        assert row["paper_ols"] == pub["ols"] and row["paper_ours"] == pub["ours"]
        assert row["ratio_svr"] == pytest.approx(row["svr"] / pub["ours"])
        assert row["gamma"] == 0.05 and row["n_N"] == 3 and row["reps_per_N"] == 4
    md = rpt.table2_markdown(rows)
    assert "published" in md and md.count("\n| paper-") == len(rows)
    parsed = list(csv.DictReader(io.StringIO(rpt.table2_csv(rows))))
    assert len(parsed) == len(rows)
    assert float(parsed[0]["svr"]) == rows[0]["svr"]  # full precision in the CSV


def test_table2_without_gamma_005_has_no_published_values():
    rows = rpt.table2(make_records(tiny_spec(gamma=[0.01]), cost=False))
    assert rows and all(r["gamma"] == 0.01 for r in rows)
    assert all(r["paper_ols"] is None and r["ratio_svr"] is None for r in rows)


# ---------------------------------------------------------------------------
# findings against hand counts
# ---------------------------------------------------------------------------


def find(lines, pattern):
    hits = [line for line in lines if re.search(pattern, line)]
    assert hits, f"no finding matches {pattern!r}:\n" + "\n".join(lines)
    return hits[0]


def test_findings_estimate_and_bounds_hand_counts():
    spec = tiny_spec()
    recs = make_records(spec, seed=1, cost=False)
    # coverage: two (system, sigma_w, N, estimator, gamma) groups pushed below 1 - delta
    low = [
        r
        for r in recs
        if r["system"] == "paper-stable"
        and r["sigma_w"] == 0.1
        and r["estimator"] == "svr"
        and r["gamma"] == 0.1
        and r["N"] in (10, 20)
    ]
    for r in low:
        r["coverage_A"] = 8 / 9
    # one record with one entry outside in another group, mean stays above 0.99? no: 1 of 4
    # reps at 8/9 gives a mean of 0.972 < 0.99 -> that is a third group; keep it out.
    # Theorem 1: exactly 3 violations for A, none for B
    for r in recs[5:8]:
        r["thm1_holds_A"] = False
    # SVR beats OLS on A for gamma 0.1 only, for every (system, sigma_w); never on B
    ols = {
        (r["system"], r["sigma_w"], r["N"], r["rep"]): r for r in recs if r["estimator"] == "ols"
    }
    for r in recs:
        if r["estimator"] == "svr":
            o = ols[(r["system"], r["sigma_w"], r["N"], r["rep"])]
            r["rmse_A"] = o["rmse_A"] * (0.9 if r["gamma"] == 0.1 else 1.1)
            r["rmse_B"] = o["rmse_B"] * 1.05
    # stable_certified: paper-stable, sigma_w 10, svr gamma 0.01: certified in 2 of 4
    # reps from N = 20 on (first N = 20), never elsewhere
    for r in recs:
        r["stable_certified"] = (
            r["system"] == "paper-stable"
            and r["sigma_w"] == 10.0
            and r["gamma"] == 0.01
            and r["N"] >= 20
            and r["rep"] < 2
        )
    lines = rpt.findings(recs, spec)
    n_groups = 2 * 2 * 3 * 3  # systems x sigma_w x N x (ols + 2 gammas)
    n_rec = len(recs)
    assert find(lines, r"Lemma 2 intervals for A").count(f"in 2 of {n_groups} ") == 1
    assert f"{len(low)} of {n_rec} " in find(lines, r"Lemma 2 intervals for A")
    assert find(lines, r"Lemma 2 intervals for A").startswith("[does not hold]")
    assert find(lines, r"Lemma 2 intervals for B").startswith("[holds]")
    assert f"violated in 3 of {n_rec} " in find(lines, r"Theorem 1 for A")
    assert f"violated in 0 of {n_rec} " in find(lines, r"Theorem 1 for B")
    for system in ("paper-stable", "paper-unstable"):
        for sw in ("0.1", "10"):
            line = find(lines, rf"SVR beats OLS in mean RMSE for {system}, σ_w={sw}:")
            assert "A: 1 of 2 γ (0.1)" in line
    # at the largest sigma_w: A wins 1 of 2 gammas per system, B none -> 2 of 8 cells
    table_claim = find(lines, r"^\[partly\] Paper .*Table 2")
    assert "2 of 8 " in table_claim and "over all 16 cells SVR wins 4" in table_claim
    cert = find(lines, r"holds in ≥ half the repetitions, paper-stable")
    assert "σ_w=10 SVR γ=0.01: N=20 (N0=200)" in cert
    assert "Never in the grid (N ≤ 30) for 5 of 6" in cert
    # the grid stops at N0 = 300 < 1800: the paper's claim cannot be tested here ... but
    # stable_certified does hold from N0=200, which is before 1800
    assert find(lines, r"determined to be stable").startswith("[holds]")
    assert "stable_certified is true in 0 of" in find(lines, r"Soundness on paper-unstable")
    svr_ols = find(lines, r"SVR and OLS estimates of A on the same data")
    assert "γ=0.01" in svr_ols and "γ=0.1" in svr_ols


def test_findings_cost_hand_counts():
    # E4's structure (S and U), with a Monte Carlo J on the first repetitions as in E3
    spec = dict(paper_specs("reduced")["E4"], mc_reps=paper_specs("reduced")["E3"]["mc_reps"])
    recs = make_records(spec, seed=2)
    for r in recs:  # make every delta_J positive, then exactly 4 negative on S, 1 on U
        r["delta_J"] = abs(r["delta_J"]) + 0.1
    s_cells = [r for r in recs if r["system"] == "paper-stable"]
    u_cells = [r for r in recs if r["system"] == "paper-unstable"]
    for r in s_cells[:4]:
        r["delta_J"] = -1.0
    u_cells[7]["delta_J"] = -0.5
    # Monte Carlo: one disagreement (more than 4 standard errors)
    mc = [r for r in recs if r["J_mc"] is not None]
    mc[0]["J_mc"] = mc[0]["J_exact"] + 1.0
    # one certified gain that is not stable for the true A
    cert = [r for r in recs if r["certified"]]
    cert[0]["rho_true"] = 1.2
    lines = rpt.findings(recs, spec)
    s = find(lines, r"Deviations are above 0.*On paper-stable")
    assert f"< 0 in 4 of {len(s_cells)} " in s and s.startswith("[does not hold]")
    u = find(lines, r"Deviations are above 0.*On paper-unstable")
    assert f"< 0 in 1 of {len(u_cells)} " in u
    n_mc = len(mc)
    assert f"in {n_mc - 1} of {n_mc} " in find(lines, r"Monte Carlo J agrees")
    n_cert_s = sum(1 for r in s_cells if r["certified"])
    line = find(lines, r"Certified gains \(g\(L\) < 1\) on paper-stable")
    assert f"ρ(A − LC) ≥ 1 − 10⁻¹⁰ for the true A: 1 of {n_cert_s} " in line
    assert line.startswith("[does not hold]")
    find(lines, r"cost variance is much larger.*On paper-stable")


def test_soundness_findings_use_the_certificates_stability_rule():
    """ρ within 10⁻¹⁰ of 1 is not Schur-stable for the certificates
    (``norms.schur_stable``), so a certificate there is counted as unsound: both for
    stable_certified on a true A of ρ = 1 − 10⁻¹² and for a certified gain with
    ρ(A − LC) = 1 − 10⁻¹² (a plain ρ ≥ 1 called both sound)."""
    spec = dict(paper_specs("reduced")["E4"])
    recs = make_records(spec, seed=2)
    edge = {"name": "edge", "A": [[1 - 1e-12, 0.0], [0.0, 0.5]], "B": [[1.0], [0.0]]}
    spec["systems"] = [*spec["systems"], edge]
    extra = [dict(r, system="edge", stable_certified=True) for r in recs[:3]]
    cert = [r for r in recs if r["certified"] and r["system"] == "paper-stable"]
    for r in cert:
        r["rho_true"] = 0.5
    cert[0]["rho_true"] = 1 - 1e-12
    lines = rpt.findings(recs + extra, spec)
    assert find(lines, r"Soundness on edge").startswith("[does not hold]")
    line = find(lines, r"Certified gains \(g\(L\) < 1\) on paper-stable")
    assert f"for the true A: 1 of {len(cert)} " in line and line.startswith("[does not hold]")


def test_findings_report_stages_without_data():
    spec = paper_specs("reduced")["E3"]
    recs = make_records(spec, cost=False)  # gain/cost fields all null
    lines = rpt.findings(recs, spec)
    for stage in ("gain", "cost", "cost_bound"):
        assert any(line.startswith("[no data] Stage '" + stage + "'") for line in lines)


def test_first_stable_certified():
    recs = make_records(tiny_spec(N=[10, 20, 30, 40]), cost=False)
    for r in recs:
        r["stable_certified"] = r["N"] >= 30 and r["rep"] < 2  # 2 of 4 reps: exactly half
        if r["system"] == "paper-unstable":
            r["stable_certified"] = False
    first = rpt.first_stable_certified(recs)
    assert first[("paper-stable", 0.1, "svr", 0.01)]["N"] == 30
    assert first[("paper-stable", 0.1, "svr", 0.01)]["N0"] == 300
    assert first[("paper-stable", 10.0, "ols", None)]["N"] == 30
    assert first[("paper-unstable", 0.1, "svr", 0.1)]["N"] is None
    assert (
        rpt.first_stable_certified(recs, share=0.75)[("paper-stable", 0.1, "svr", 0.01)]["N"]
        is None
    )


# ---------------------------------------------------------------------------
# figures
# ---------------------------------------------------------------------------


def texts(fig):
    return [t.get_text() for ax in fig.axes for t in ax.texts]


def test_cost_figures_with_constructed_records():
    spec = paper_specs("reduced")["E4"]
    recs = make_records(spec, seed=4)
    for fn in (rpt.fig4, rpt.fig5, rpt.fig_certified):
        fig = fn(recs, spec, experiment="E4")
        assert not any(t.startswith("no data") for t in texts(fig)), fn.__name__
        assert any(ax.lines for ax in fig.axes)
        assert "E4" in fig._suptitle.get_text() and "seed 0" in fig._suptitle.get_text()
    png = rpt.figure_bytes(rpt.fig4(recs, spec), "png")
    assert png.startswith(PNG_MAGIC)


def test_cost_ratio_of_means_is_computed_from_the_records():
    spec = paper_specs("reduced")["E4"]
    recs = make_records(spec, seed=5)
    cols = rpt.as_columns(recs)
    _, Ns, r = rpt.cost_ratio_of_means(cols, "paper-unstable", 0.01, 0.1)
    for N, value in zip(Ns, r):
        J = [
            x["J_exact"]
            for x in recs
            if x["system"] == "paper-unstable" and x["N"] == N and x["gamma"] == 0.01
        ]
        Jr = [
            x["J_exact"]
            for x in recs
            if x["system"] == "paper-unstable" and x["N"] == N and x["gamma"] == 0.1
        ]
        mj, mr = sum(J) / len(J), sum(Jr) / len(Jr)
        assert value == pytest.approx(abs(mj - mr) / mr, rel=1e-12)


def test_figures_show_no_data_instead_of_crashing():
    spec = paper_specs("reduced")["E4"]
    recs = make_records(spec, cost=False)
    for fn in (rpt.fig4, rpt.fig5, rpt.fig_certified):
        fig = fn(recs, spec)
        assert any(t.startswith("no data") for t in texts(fig)), fn.__name__
        assert rpt.figure_bytes(fig, "svg").lstrip().startswith(b"<?xml")
    fig = rpt.fig2([], None)
    assert any(t.startswith("no data") for t in texts(fig))


def test_figure_titles_name_experiment_and_seed():
    spec = tiny_spec(seed=7)
    recs = make_records(spec, cost=False)
    for r in recs:  # some coverage below 1, else fig_coverage has nothing to draw
        if r["rep"] == 0 and r["N"] == 10:
            r["coverage_A"] = 0.75
    for fn in (rpt.fig_rmse, rpt.fig2, rpt.fig3, rpt.fig_coverage, rpt.fig_svr_ols_diff):
        fig = fn(recs, spec, experiment="X9")
        title = fig._suptitle.get_text()
        assert "X9" in title and "seed 7" in title, fn.__name__
        rows = {ax.get_subplotspec().rowspan.start for ax in fig.axes if ax.lines}
        labelled = {ax.get_subplotspec().rowspan.start for ax in fig.axes if ax.get_ylabel()}
        assert rows and rows <= labelled, fn.__name__  # every row of panels has a y label
        assert any(ax.get_xlabel() for ax in fig.axes), fn.__name__
        assert fig.legends, fn.__name__


def test_coverage_of_one_everywhere_is_a_note_not_a_figure():
    spec = tiny_spec()
    recs = make_records(spec, cost=False)  # coverage 1 in every record
    fig = rpt.fig_coverage(recs, spec)
    assert fig.svrobs_empty and not fig.axes
    assert f"is 1 in all {len(recs):,} records" in fig.svrobs_notes[0]
    for r in recs:  # B below 1 somewhere: only the A rows are left out
        r["coverage_B"] = 0.5 if r["rep"] == 0 else 1.0
    fig = rpt.fig_coverage(recs, spec)
    assert len(fig.axes) == 2 * 2 and all(ax.get_title().endswith(": B") for ax in fig.axes)
    assert f"The coverage of A is 1 in all {len(recs):,} records" in fig.svrobs_notes[0]
    recs = make_records(spec, cost=False)
    rep = rpt.build_report({"X": {"spec": spec, "records": recs}})
    md = rpt.render_markdown(rep)
    assert "fig_coverage.png" not in md and f"is 1 in all {len(recs):,} records" in md


def test_a_figure_is_drawn_only_from_an_experiment_with_its_fields():
    spec = tiny_spec()
    est = make_records(spec, cost=False)  # no delta_J, J_exact
    cost_spec = paper_specs("reduced")["E4"]
    full = make_records(cost_spec, seed=4)
    rep = rpt.build_report({"E1": {"spec": spec, "records": est}})
    titles = {f.name: f.experiment for f in rep.figures}
    assert "fig4" not in titles and "fig5" not in titles and titles["fig_rmse"] == "E1"
    assert [t.split(":")[0] for t, _ in rep.figures_not_drawn if t.startswith("Fig.")] == [
        "Fig. 4",
        "Fig. 5",
    ]
    both = rpt.build_report(
        {"E1": {"spec": spec, "records": est}, "X": {"spec": cost_spec, "records": full}}
    )
    assert {f.name: f.experiment for f in both.figures}["fig4"] == "X"  # the one that has it
    assert not [t for t, _ in both.figures_not_drawn if t.startswith("Fig. 4")]


def test_svr_ols_difference_uses_the_same_repetition():
    recs = make_records(tiny_spec(), cost=False)
    cols = rpt.as_columns(recs)
    d = rpt.svr_ols_diff(cols)
    by_key = {
        (r["system"], r["sigma_w"], r["N"], r["rep"]): r for r in recs if r["estimator"] == "ols"
    }
    for i, r in enumerate(recs):
        if r["estimator"] != "svr":
            assert math.isnan(d[i])
            continue
        o = by_key[(r["system"], r["sigma_w"], r["N"], r["rep"])]
        want = np.abs(np.array(r["A_hat"]) - np.array(o["A_hat"])).max()
        assert d[i] == pytest.approx(want, rel=1e-12)


# ---------------------------------------------------------------------------
# reproduce: planning and missing stages (no rendering)
# ---------------------------------------------------------------------------


def test_plan_takes_sub_grids_from_their_parents_and_shares_their_data():
    specs = paper_specs("reduced")
    # A1 (self-normalized) and A2 (bootstrap) have E2's grid and data but not its
    # bounds: they run in E2's pass; E1 and E3 are selections of E2's and E4's records
    plan = [(g.parent, g.variants, g.children) for g in reproduce_plan.plan(specs, derive=True)]
    assert plan == [("E2", ["A1", "A2"], ["E1"]), ("E4", [], ["E3"])]
    full = [(g.parent, g.variants, g.children) for g in reproduce_plan.plan(paper_specs("full"))]
    assert full == plan  # A2 on five of E2's N values
    assert [g.names for g in reproduce_plan.plan(specs, derive=False)] == [[n] for n in specs]
    assert not reproduce_plan.derivable(specs["E2"], specs["A1"])
    assert not reproduce_plan.derivable(specs["A1"], specs["E2"])
    other_seed = dict(specs["E1"], seed=1)
    assert not reproduce_plan.derivable(other_seed, specs["E2"])
    swapped = dict(specs["E3"], systems=["paper-unstable"])  # index 0 in E3, 1 in E4
    assert not reproduce_plan.derivable(swapped, specs["E4"])


def test_the_group_with_the_most_experiments_runs_first_then_the_most_records():
    specs = paper_specs("full")
    groups = reproduce_plan.plan(specs)
    # E4's group holds more records (E4 + E3: 540,000 against 152,550), but E2's has four
    # experiments, six figures: its report part is made while E4's units run
    cells = {n: parse_spec(s).n_cells for n, s in specs.items()}
    assert cells["E4"] + cells["E3"] > cells["E2"] + cells["A1"] + cells["A2"] + cells["E1"]
    order = [g.names for g in reproduce_plan.run_order(groups, specs)]
    assert order == [["E2", "A1", "A2", "E1"], ["E4", "E3"]]
    # between groups of as many experiments, the one with more records first
    solo = reproduce_plan.plan({"E1": specs["E1"], "E4": specs["E4"]}, derive=False)
    assert [g.names for g in reproduce_plan.run_order(solo, specs)] == [["E4"], ["E1"]]
    fewer = dict(specs["E3"], gamma=[0.05, 0.1])  # the cost ratio couples the gammas
    assert not reproduce_plan.derivable(fewer, specs["E4"])
    only = reproduce_plan.select_experiments(specs, "E1, A2")
    assert [(g.parent, g.variants, g.children) for g in reproduce_plan.plan(only)] == [
        ("E1", [], []),
        ("A2", [], []),
    ]
    with pytest.raises(rep_mod.ReproduceError, match="unknown experiment E9"):
        reproduce_plan.select_experiments(specs, "E1,E9")


def test_unit_texts_are_appended_in_unit_order_whatever_order_units_finish(tmp_path):
    """Each experiment's records.jsonl is its units' parts in unit order, appended as
    soon as every earlier unit is in; a part on disk is one waiting for an earlier
    unit; a unit with no text for an experiment (another system) is skipped."""
    group = reproduce_plan.Group("P", children=["C"])
    run = rep_mod._GroupRun(group=group, specs=(), units=[{}] * 5, outputs=[])
    for n in group.names:
        (tmp_path / n / ".parts").mkdir(parents=True)
        run.parts[n] = {}
        run.files[n] = open(tmp_path / n / "records.jsonl", "wb", buffering=0)
    text = {("P", ui): f"p{ui}a\np{ui}b\n" for ui in range(5)}
    text.update({("C", ui): f"c{ui}\n" for ui in (0, 2, 3)})  # C has no cells in units 1, 4
    waiting = {2: {2}, 4: {2, 4}, 0: {2, 4}, 1: {4}, 3: set()}
    for ui in (2, 4, 0, 1, 3):  # the order the units finish
        for n in group.names:
            if (n, ui) in text:
                rep_mod._part(tmp_path, n, ui).write_text(text[n, ui])
                run.parts[n][ui] = ui
        run.done.add(ui)
        rep_mod._append_ready(run, tmp_path)
        on_disk = {int(p.stem) for p in (tmp_path / "P" / ".parts").glob("*.jsonl")}
        assert on_disk == waiting[ui], ui
    rep_mod._close(run)
    for n in group.names:
        want = "".join(text[n, ui] for ui in range(5) if (n, ui) in text)
        assert (tmp_path / n / "records.jsonl").read_text() == want
        assert run.parts[n] == sorted(run.parts[n])  # the report's columns in unit order
    assert not list((tmp_path / "C" / ".parts").iterdir())


def test_a_failing_stage_stops_the_reproduction_naming_it(tmp_path, monkeypatch):
    """No stage is dropped: the run stops, naming the experiment, the stage and why."""
    from svrobs_core import pipeline, uncertainty

    def missing(*args, **kwargs):
        raise NotImplementedError("observer pipeline not yet written")

    monkeypatch.setattr(pipeline, "design", missing)
    with pytest.raises(rep_mod.ReproduceError) as exc:
        rep_mod.reproduce(tmp_path, scale="reduced", quiet=True, n_jobs=1, only="E3")
    assert str(exc.value) == (
        "E3: stage 'gain' failed: NotImplementedError: observer pipeline not yet written"
    )
    assert not (tmp_path / "report.md").exists()
    # nothing of the stopped group is left: no partial records.jsonl, no part file
    assert not (tmp_path / "E3" / "records.jsonl").exists()
    assert not list(tmp_path.glob("*/.parts"))
    monkeypatch.setattr(uncertainty, "bootstrap_box", missing)
    with pytest.raises(rep_mod.ReproduceError, match="^A2: stage 'bounds' failed: NotImpl"):
        rep_mod.reproduce(tmp_path, scale="reduced", quiet=True, n_jobs=1, only="E2,A1,A2")


def test_a_failure_outside_the_stages_is_not_put_on_one(tmp_path, monkeypatch):
    def full(*args, **kwargs):
        raise OSError("No space left on device")

    monkeypatch.setattr(rep_mod, "_part", full)
    with pytest.raises(rep_mod.ReproduceError) as exc:
        rep_mod.reproduce(tmp_path, scale="reduced", quiet=True, n_jobs=1, only="E1")
    assert str(exc.value) == "E1: failed outside its stages: OSError: No space left on device"


# ---------------------------------------------------------------------------
# reproduce end to end on the reduced grid, real pipeline
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def reproduced(tmp_path_factory):
    out = tmp_path_factory.mktemp("reproduce")
    result = rep_mod.reproduce(out, scale="reduced", quiet=True)
    return out, result


def drawn_figures(out):
    return [f for f in FIGURES if (out / f"{f}.png").exists()]


def read_jsonl(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_reproduce_writes_every_file(reproduced):
    out, result = reproduced
    for name in ("table2.md", "table2.csv", "report.md", "report.html", "provenance.json"):
        assert (out / name).stat().st_size > 0, name
    md = (out / "report.md").read_text()
    for fig in drawn_figures(out):
        assert (out / f"{fig}.png").read_bytes().startswith(PNG_MAGIC), fig
        svg = (out / f"{fig}.svg").read_text()
        assert "<svg" in svg and svg.rstrip().endswith("</svg>"), fig
        assert (out / f"{fig}.pdf").read_bytes().startswith(b"%PDF-"), fig
        header = (out / f"{fig}.csv").read_text().splitlines()[0]
        assert header == "panel,series,quantity,N0,value", fig
    for fig in set(FIGURES) - set(drawn_figures(out)):
        # only a figure with nothing to plot is left out, and the report says why
        assert fig == "fig_coverage" and "coverage of A and B is 1 in all" in md
    for exp in ("E1", "E2", "E3", "E4", "A1", "A2"):
        recs = read_jsonl(out / exp / "records.jsonl")
        assert len(recs) == result["records"][exp] > 0
        assert all(tuple(r) == RECORD_FIELDS for r in recs[:5])
        assert parse_spec(json.loads((out / exp / "spec.json").read_text())["spec"])


def test_reproduce_record_counts(reproduced):
    _, result = reproduced
    specs = paper_specs("reduced")
    for exp, s in specs.items():
        assert result["records"][exp] == parse_spec(s).n_cells


def test_reproduce_table2_against_independent_computation(reproduced):
    out, _ = reproduced
    ind = independent_table(read_jsonl(out / "E1" / "records.jsonl"))
    rows = list(csv.DictReader(io.StringIO((out / "table2.csv").read_text())))
    assert len(rows) == 2 * 3 * 2
    for row in rows:
        key = (row["system"], float(row["sigma_w"]), row["matrix"])
        assert float(row["ols"]) == pytest.approx(ind[key + ("ols",)], rel=1e-12)
        assert float(row["svr"]) == pytest.approx(ind[key + ("svr",)], rel=1e-12)
        # the reduced grid (N in 10..50) is not the paper's: no published values beside it
        assert row["paper_ols"] == row["paper_ours"] == row["ratio_ols"] == ""
    md = (out / "table2.md").read_text()
    assert f"{float(rows[0]['ols']):.4g}" in md
    assert "published Table 2 values are not shown" in md and "45 values 10..450" in md
    assert "published Table 2 values are not shown" in (out / "report.html").read_text()


def test_table2_published_only_beside_the_paper_grid(reproduced):
    """The same records tabulated under the paper's E1 spec get the published values
    and ratios; under the reduced spec, none and the reason."""
    out, _ = reproduced
    recs = read_jsonl(out / "E1" / "records.jsonl")
    paper = table2(recs, spec=paper_specs("full")["E1"])
    assert all(r["paper_note"] is None for r in paper)
    for row in paper:
        pub = PUBLISHED_TABLE2[(row["system"], row["sigma_w"], row["matrix"])]
        assert (row["paper_ols"], row["paper_ours"]) == (pub["ols"], pub["ours"])
        assert row["ratio_ols"] == pytest.approx(row["ols"] / pub["ols"], rel=1e-12)
    other = table2(recs, spec=paper_specs("reduced")["E1"])
    assert [r["ols"] for r in other] == [r["ols"] for r in paper]
    assert all(r["paper_ols"] is None and r["ratio_svr"] is None for r in other)
    assert "N has 3 values 10..50" in other[0]["paper_note"]


def test_derived_e1_equals_a_direct_run(reproduced):
    out, _ = reproduced
    derived = read_jsonl(out / "E1" / "records.jsonl")
    direct = [r for batch in run_spec(parse_spec(paper_specs("reduced")["E1"])) for r in batch]

    def key(r):
        return (r["system"], r["sigma_w"], r["N"], r["rep"], r["estimator"], r["gamma"])

    derived.sort(key=lambda r: tuple(str(v) for v in key(r)))
    direct.sort(key=lambda r: tuple(str(v) for v in key(r)))
    assert [key(r) for r in derived] == [key(r) for r in direct]
    for a, b in zip(derived, direct):
        np.testing.assert_allclose(a["A_hat"], b["A_hat"], rtol=1e-12, atol=1e-15)
        for f in ("rmse_A", "rmse_B", "eps_A", "r_A", "rho_upper_bound"):
            assert a[f] == pytest.approx(b[f], rel=1e-12)
        assert a["coverage_A"] == b["coverage_A"] and a["stable_certified"] == b["stable_certified"]


def test_derived_e3_and_parallel_run_equal_a_direct_run(reproduced):
    """E3's records (taken from E4's, computed in worker processes) and A1's, A2's
    (computed in E2's pass over the data) are, as JSON text, the records of each
    run on its own in this process."""
    out, _ = reproduced
    for exp in ("E3", "E4", "A1", "A2"):  # E4 has no Monte Carlo J: its S records are E3's
        derived = (out / exp / "records.jsonl").read_text().splitlines()
        direct = [
            json.dumps(r, allow_nan=False)
            for batch in run_spec(parse_spec(paper_specs("reduced")[exp]))
            for r in batch
        ]
        assert derived == direct, exp


def test_report_contents(reproduced):
    out, _ = reproduced
    md = (out / "report.md").read_text()
    assert "## Findings" in md and "## Table 2" in md and "## Provenance" in md
    assert "published" in md
    for fig in drawn_figures(out):
        for ext in ("png", "svg", "pdf", "csv"):
            assert f"({fig}.{ext})" in md
    for exp in ("E1", "E2", "E3", "E4", "A1", "A2"):
        assert f"### {exp}:" in md
    # the uncertainty-set audit: one table row per (method, system, sigma_w, estimator)
    audit = md[md.index("## Beyond the paper: uncertainty sets") : md.index("## Figures")]
    for method in ("paper", "self-normalized", "bootstrap"):
        assert len(re.findall(rf"^\| {method} \| paper-", audit, flags=re.M)) == 2 * 3 * 2
        assert re.search(rf"^- \[(holds|does not hold)\] {method}: ", audit, flags=re.M)
    # findings with counts for the estimate/bounds claims
    assert re.search(r"Theorem 1 for A \(every row\): violated in \d+ of \d+", md)
    assert re.search(r"below 1 − δ = 0.99 in \d+ of \d+", md)
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64,") == len(drawn_figures(out))
    assert "<h2>Findings" in html and "paper-section-6" in html
    assert "<h2>Beyond the paper: uncertainty sets" in html
    prov = json.loads((out / "provenance.json").read_text())
    assert prov["preset"] == "paper-section-6" and prov["scale"] == "reduced"
    assert prov["derived_from"] == {"E1": "E2", "E3": "E4"}
    assert prov["shares_data_of"] == {"A1": "E2", "A2": "E2"}
    assert set(prov["normals"]) == set(paper_specs("reduced")) and prov["normals"]["E1"] == 0
    assert prov["draws"] == dict.fromkeys(paper_specs("reduced"), "wishart")


def test_cli_reproduce_runs_a_subset_and_refuses_unknown_names(tmp_path):
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "svrobs_cli", "reproduce", "--scale", "reduced", "--quiet"]
    done = subprocess.run(
        [*cmd, "--only", "E1", "--jobs", "1", "--draws", "rollouts", "--out", str(tmp_path / "t2")],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in (tmp_path / "t2").iterdir() if p.is_dir()) == ["E1"]
    prov = json.loads((tmp_path / "t2" / "provenance.json").read_text())
    assert prov["experiments"] == ["E1"] and prov["records"]["E1"] == 2 * 3 * 3 * 3 * 2
    assert prov["draws"] == {"E1": "rollouts"}  # the preset's "wishart", overridden
    assert not list((tmp_path / "t2" / "E1").glob(".parts*"))
    md = (tmp_path / "t2" / "report.md").read_text()  # E1 has no cost and no gain stage:
    for title, needs in (("Fig. 4", "delta_J"), ("Fig. 5", "J_exact")):  # not drawn, said
        assert f"- Not drawn: {title}" in md and f"no experiment here has {needs})" in md
    assert "fig4.png" not in md and not (tmp_path / "t2" / "figures" / "fig4.png").exists()
    assert "![RMSE per sample length" in md  # what E1 has is drawn
    bad = subprocess.run(
        [*cmd, "--only", "E1,E9", "--out", str(tmp_path / "bad")],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines() == [
        "error: reproduce: --only: unknown experiment E9; the preset has E1, E2, E3, E4, A1, A2"
    ]
    bad = subprocess.run([*cmd, "--draws", "bartlett"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines() == ["error: --draws must be one of rollouts, wishart"]


def test_the_published_table_2_is_what_the_full_preset_writes(tmp_path):
    """docs/table2.md and the README's Table 2 are the full preset's E1 as
    `svrobs reproduce` writes it today (the default draws), byte for byte."""
    rep_mod.reproduce(tmp_path, scale="full", quiet=True, n_jobs=1, only="E1")
    written = (tmp_path / "table2.md").read_text()
    root = Path(__file__).resolve().parents[2]
    assert (root / "docs" / "table2.md").read_text() == written
    readme = (root / "README.md").read_text()
    for row in (line for line in written.splitlines() if line.startswith("| paper-")):
        assert row in readme, row
