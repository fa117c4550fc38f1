"""The runner (docs/spec.md#record-fields): records contract and bit-identical reproducibility."""

import json
import subprocess
import sys

import numpy as np
import pytest

from svrobs_core import RECORD_FIELDS, parse_spec, plan_units, run_spec, run_unit
from svrobs_core.rollouts import collect
from svrobs_core.seeding import seed_key

ALL_STAGES = ["estimate", "bounds", "gain", "cost", "cost_bound"]
SMALL = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.1, 1.0],
    "N": [10, 30],
    "gamma": [0.01, 0.1],
    "estimators": ["ols", "svr", "shrunk-ols"],
    "reps": 3,
    "stages": ALL_STAGES,
    "mc_runs": 400,
    "mc_reps": 1,
    "horizon": 40,
    "seed": 11,
}


def records(spec, units=None):
    return [r for batch in run_spec(spec, units=units) for r in batch]


def key(r):
    return (r["system"], r["sigma_w"], r["N"], r["estimator"], r["gamma"], r["rep"])


@pytest.fixture(scope="module")
def small():
    spec = parse_spec(SMALL)
    return spec, records(spec)


def test_fields_are_exactly_the_contract_and_json_has_no_nan(small):
    spec, recs = small
    assert len(recs) == spec.n_cells == 2 * 2 * 2 * 3 * 5
    for r in recs:
        assert tuple(r) == RECORD_FIELDS
    text = json.dumps(recs, allow_nan=False)  # raises on NaN/inf
    assert "NaN" not in text


def test_cells_one_by_one_equal_all_at_once_bit_for_bit(small):
    spec, recs = small
    one_by_one = records(spec, units=plan_units(spec, max_cells=1, target_cells=1))
    assert len(plan_units(spec, max_cells=1, target_cells=1)) == 2 * 2 * 2 * 3
    assert [u["N"] for u in plan_units(spec)][:1] == [[10, 30]]  # the default packs N values
    a = {key(r): r for r in recs}
    b = {key(r): r for r in one_by_one}
    assert a.keys() == b.keys()
    for k in a:
        assert json.dumps(a[k]) == json.dumps(b[k]), k


def test_estimators_and_gammas_see_the_same_data(small):
    spec, recs = small
    # OLS from an independent fit on the rollouts of one key equals the stored A_hat
    r = next(
        x
        for x in recs
        if x["estimator"] == "ols"
        and x["system"] == "paper-unstable"
        and x["N"] == 30
        and x["rep"] == 2
        and x["sigma_w"] == 1.0
    )
    Z, F = collect(spec.systems[1], 1.0, 30, 11, seed=11, keys=[seed_key(1, 1, 30, 2)])
    theta = np.linalg.lstsq(Z[0].T, F[0].T, rcond=None)[0].T
    np.testing.assert_allclose(r["A_hat"], theta[:, :3], rtol=1e-10, atol=1e-12)
    # a spec with fewer gammas gives the same numbers for the gammas it shares
    fewer = parse_spec({**SMALL, "gamma": [0.1], "estimators": ["svr", "ols"]})
    b = {key(x): x for x in records(fewer)}
    a = {key(x): x for x in recs}
    for k, rec in b.items():
        for f in ("A_hat", "B_hat", "rmse_A", "eps_A", "L", "J_exact", "J_mc"):
            assert rec[f] == a[k][f], (k, f)


def test_same_seed_same_records_other_seed_other_data():
    spec = parse_spec({**SMALL, "systems": ["paper-stable"], "stages": ["estimate"]})
    again = records(spec)
    assert json.dumps(again) == json.dumps(records(spec))
    other = records(
        parse_spec({**SMALL, "systems": ["paper-stable"], "stages": ["estimate"], "seed": 12})
    )
    assert again[0]["A_hat"] != other[0]["A_hat"]


def test_null_fields_have_notes(small):
    _, recs = small
    for r in recs:
        if r["system"] == "paper-unstable":
            assert r["J_bound"] is None and r["J_stationary"] is None
            assert "J_bound" in r["notes"] and "J_stationary: unstable" in r["notes"]
        if r["rep"] >= 1:
            assert r["J_mc"] is None and "J_mc" in r["notes"]
        if r["J_mc"] is not None:
            # exact and Monte Carlo agree within 4 standard errors
            # (docs/science.md#6-observer-cost-j)
            assert abs(r["J_mc"] - r["J_exact"]) < 4 * r["J_mc_se"] + 1e-12
    est_only = records(parse_spec({**SMALL, "stages": ["estimate"], "reps": 1}))
    assert all(r["L"] is None and "stages not run: bounds, gain" in r["notes"] for r in est_only)


def test_cost_ratio_against_gamma_ref(small):
    _, recs = small
    by = {key(r): r for r in recs}
    for k, r in by.items():
        if r["estimator"] == "svr":
            ref = by[k[:4] + (0.1, k[5])]
            expect = abs(r["J_exact"] - ref["J_exact"]) / ref["J_exact"]
            assert r["cost_ratio"] == pytest.approx(expect, rel=1e-12)
        if r["estimator"] == "ols":
            assert r["cost_ratio"] is None


def test_reuse_gain_keeps_a_certified_gain_along_N():
    base = {
        "systems": ["paper-stable"],
        "sigma_w": [0.1],
        "N": [100, 200, 300],
        "gamma": [0.005],
        "estimators": ["svr"],
        "reps": 2,
        "stages": ["estimate", "bounds", "gain"],
    }
    fresh = {key(r): r for r in records(parse_spec(base))}
    reused = records(parse_spec({**base, "reuse_gain": True}))
    assert len(plan_units(parse_spec({**base, "reuse_gain": True}))) == 1
    kept = 0
    for r in reused:
        if r["N"] == 100:
            assert r["L"] == fresh[key(r)]["L"]
            continue
        prev = next(
            x
            for x in reused
            if x["rep"] == r["rep"]
            and x["N"] < r["N"]
            and x["N"] == max(n for n in (100, 200, 300) if n < r["N"])
        )
        if r["notes"] and "reused" in r["notes"]:
            kept += 1
            assert r["L"] == prev["L"] and prev["certified"] and r["certified"]
        else:
            assert r["L"] == fresh[key(r)]["L"]
    assert kept > 0


def test_run_local_cli_writes_records_and_summary(tmp_path):
    spec = {
        **SMALL,
        "systems": ["paper-stable"],
        "sigma_w": [1.0],
        "stages": ["estimate", "bounds"],
    }
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    out = tmp_path / "out"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "svrobs_cli",
            "run-local",
            str(tmp_path / "spec.json"),
            "--out",
            str(out),
            "--quiet",
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
    lines = (out / "records.jsonl").read_text().splitlines()
    recs = [json.loads(x) for x in lines]
    assert len(recs) == parse_spec(spec).n_cells
    summary = json.loads((out / "summary.json").read_text())
    g = next(
        x
        for x in summary["groups"]
        if x["estimator"] == "svr" and x["gamma"] == 0.01 and x["N"] == 30
    )
    vals = [
        r["rmse_A"] for r in recs if r["estimator"] == "svr" and r["gamma"] == 0.01 and r["N"] == 30
    ]
    assert g["stats"]["rmse_A"]["count"] == len(vals) == 3
    assert g["stats"]["rmse_A"]["mean"] == pytest.approx(sum(vals) / 3, rel=1e-12)


def test_run_local_cli_bad_spec_is_one_line_exit_2(tmp_path):
    (tmp_path / "bad.json").write_text(json.dumps({**SMALL, "reps": 0}))
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "svrobs_cli",
            "run-local",
            str(tmp_path / "bad.json"),
            "--out",
            str(tmp_path / "o"),
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == ["error: invalid spec: reps: must be >= 1"]
    assert "Traceback" not in proc.stderr + proc.stdout


# ---------------------------------------------------------------------------
# column results: JSON text, report columns, notes, worker processes
# ---------------------------------------------------------------------------
def test_value_columns_equal_those_of_each_dataset_on_its_own():
    """value_columns takes a field of every dataset in one pass when its arrays share a
    dtype: the values are those of each dataset's own UnitResult one after the other,
    also where a field is missing in one dataset or of another dtype in another."""
    import copy

    from svrobs_core.runner import run_unit_result

    spec = parse_spec({**SMALL, "N": [10, 20, 30]})
    res = run_unit_result(spec, plan_units(spec)[0])
    assert len(res.datasets) == 3
    a, b, c = res.datasets
    b.fields["rmse_A"] = None  # not computed in one dataset
    c.fields["rmse_B"] = np.asarray(c.fields["rmse_B"], dtype=object)  # another dtype
    c.fields["rmse_B"][0, 0] = np.inf
    a.fields["eps_A"] = np.full_like(a.fields["eps_A"], np.nan)
    a.fields["rmse_B"] = np.array(a.fields["rmse_B"], dtype=float)
    a.fields["rmse_B"][0, 0] = np.nan  # null here, beside the object array of c

    def alone(ds):
        one = copy.copy(res)  # the same unit with this dataset only
        one.datasets = [ds]
        return one.value_columns()

    got = res.value_columns()
    parts = [alone(ds) for ds in res.datasets]
    for f in RECORD_FIELDS:
        want = [v for p in parts for v in p[f]]
        assert [repr(v) for v in got[f]] == [repr(v) for v in want], f
    assert got["rmse_A"].count(None) == len(res.reps) * len(res.axis.names)


def test_json_lines_and_columns_equal_the_records():
    """UnitResult.json_lines() is json.dumps(record) to the byte, and
    UnitResult.columns() is what report.Columns builds from the records."""
    from svrobs_core.report import Columns
    from svrobs_core.runner import run_unit_result

    for spec_obj in (
        SMALL,
        {**SMALL, "stages": ["estimate"]},
        {**SMALL, "reuse_gain": True},
        {**SMALL, "mc_reps": 0, "gamma": [0.05]},
    ):
        spec = parse_spec(spec_obj)
        for unit in plan_units(spec):
            res = run_unit_result(spec, unit)
            recs = res.records()
            assert len(res) == len(recs)
            assert res.json_lines() == [json.dumps(r, allow_nan=False) for r in recs]
            want = Columns.from_records(recs).data
            got = res.columns()
            assert set(want) == set(got)
            for f, a in want.items():
                if a.dtype == object:
                    assert got[f].tolist() == a.tolist(), f
                else:
                    assert np.array_equal(got[f], a, equal_nan=True), f


def test_notes_match_a_per_cell_list():
    """The vectorised notes equal the obvious per-cell implementation."""
    from svrobs_core.notes import Notes

    rng = np.random.default_rng(3)
    shape = (7, 5)
    notes = Notes(shape)
    naive = [[[] for _ in range(shape[1])] for _ in range(shape[0])]
    texts = ["a", "b; c", "a", "d", "e", "b; c"] + [f"t{i}" for i in range(70)]
    for t in texts:
        mask = rng.random(shape) < 0.3
        notes.add(mask, t)
        for i, j in zip(*np.nonzero(mask)):
            if t not in naive[i][j]:
                naive[i][j].append(t)
    reasons = np.array([[None, "x", "", "y", "x"]] * 7, dtype=object)
    notes.add_reasons(reasons, "P")
    for i in range(7):
        for j in range(5):
            if reasons[i, j]:
                t = f"P: {reasons[i, j]}"
                if t not in naive[i][j]:
                    naive[i][j].append(t)
    got = notes.strings()
    for i in range(7):
        for j in range(5):
            assert got[i, j] == ("; ".join(naive[i][j]) if naive[i][j] else None)


def test_worker_processes_give_the_same_records(small):
    spec, recs = small
    par = [r for batch in run_spec(spec, n_jobs=2) for r in batch]
    assert json.dumps(par) == json.dumps(recs)


def test_records_for_a_smaller_mc_reps_equal_a_direct_run():
    from svrobs_core.runner import run_unit_result

    spec = parse_spec({**SMALL, "mc_reps": 2, "mc_runs": 50})
    for mc in (0, 1, 2):
        other = parse_spec({**SMALL, "mc_reps": mc, "mc_runs": 50})
        for unit in plan_units(spec):
            got = run_unit_result(spec, unit).with_mc_reps(mc).json_lines()
            assert got == [json.dumps(r) for r in run_unit(other, unit)]
    with pytest.raises(ValueError):
        run_unit_result(spec, plan_units(spec)[0]).with_mc_reps(3)


def test_unit_cells_counts_the_records_of_each_unit():
    from svrobs_core.planning import unit_cells

    spec = parse_spec({**SMALL, "stages": ["estimate"]})
    for units in (plan_units(spec), plan_units(spec, max_cells=7, target_cells=7)):
        assert sum(unit_cells(spec, u) for u in units) == spec.n_cells
        for u in units[:3]:
            assert unit_cells(spec, u) == len(run_unit(spec, u))
