"""The uncertainty-set audit of the report: rows recomputed here with
plain loops over hand-made records; sources, findings and the report section."""

from __future__ import annotations

import itertools
import random

import pytest

from svrobs_core.records import empty_record
from svrobs_core.report import build_report, render_markdown
from svrobs_core.report.audit import audit_findings, audit_rows, audit_sources

BASE = {
    "systems": ["paper-stable"],
    "sigma_w": [1.0],
    "N": [10, 20],
    "gamma": [0.05],
    "reps": 4,
    "delta": 0.1,
}


def _records(method: str, seed: int) -> list[dict]:
    rng = random.Random(seed)
    out = []
    for N, rep, (est, g) in itertools.product((10, 20), range(4), (("ols", None), ("svr", 0.05))):
        r = empty_record()
        r.update(
            system="paper-stable",
            sigma_w=1.0,
            N=N,
            N0=10 * N,
            estimator=est,
            gamma=g,
            rep=rep,
            bounds_method=method,
            coverage_A=rng.choice([1.0, 1.0, 8 / 9]),
            coverage_B=rng.choice([1.0, 2 / 3]),
            r_A=rng.uniform(0.1, 0.5),
            r_B=rng.uniform(0.1, 0.5),
            stable_certified=bool(N == 20 and rep < 3) or rng.random() < 0.2,
        )
        out.append(r)
    return out


def _expected(recs: list[dict], est: str) -> dict:
    mine = [r for r in recs if r["estimator"] == est]
    n = len(mine)
    first = None
    for N in (10, 20):
        at = [r["stable_certified"] for r in mine if r["N"] == N]
        if sum(at) / len(at) >= 0.5:
            first = N
            break
    return {
        "records": n,
        "coverage_A": sum(r["coverage_A"] for r in mine) / n,
        "coverage_B": sum(r["coverage_B"] for r in mine) / n,
        "simultaneous": sum(r["coverage_A"] == 1 and r["coverage_B"] == 1 for r in mine) / n,
        "r_A": sum(r["r_A"] for r in mine) / n,
        "r_B": sum(r["r_B"] for r in mine) / n,
        "first_N": first,
    }


def test_audit_rows_match_a_loop():
    sources = {"paper": _records("paper", 1), "self-normalized": _records("self-normalized", 2)}
    rows = audit_rows(sources, 0.1)
    assert [(r["method"], r["estimator"]) for r in rows] == [
        ("paper", "svr"),
        ("paper", "ols"),
        ("self-normalized", "svr"),
        ("self-normalized", "ols"),
    ]
    for r in rows:
        want = _expected(sources[r["method"]], r["estimator"])
        for k, v in want.items():
            assert r[k] == (pytest.approx(v) if isinstance(v, float) else v), (r["method"], k)
    found = audit_findings(rows, 0.1)
    assert len(found) == 2
    for f, method in zip(found, sources):
        worst = min(r["simultaneous"] for r in rows if r["method"] == method)
        assert f.startswith("[holds]" if worst >= 0.9 else "[does not hold]")
        assert f" {method}: " in f


def test_sources_and_report_section():
    exps = {
        "E2": {"spec": BASE, "records": _records("paper", 1)},
        "A1": {"spec": {**BASE, "bounds_method": "self-normalized"}, "records": _records("sn", 2)},
    }
    # the method comes from the spec, not from the records
    assert audit_sources(exps, {n: _cols(e) for n, e in exps.items()}) == {
        "paper": "E2",
        "self-normalized": "A1",
    }
    rep = build_report(exps)
    assert rep.audit_sources == {"paper": "E2", "self-normalized": "A1"}
    assert len(rep.audit) == 4 and rep.figures[-1].name == "fig_bounds_audit"
    md = render_markdown(rep)
    assert "## Beyond the paper: uncertainty sets" in md
    only_paper = build_report({"E2": exps["E2"]})
    assert only_paper.audit == [] and "fig_bounds_audit" not in [f.name for f in only_paper.figures]


def _cols(e):
    from svrobs_core.report import as_columns

    return as_columns(e["records"])
