"""Admission (svrobs_core.admission): size caps from the axis lengths first, the
closed-form cost of the grid, units under the per-unit CPU cap.

The oracle of the closed form is the per-unit sum: every unit of plan_units
costed one N at a time, as the cost model did before it was summed over the axes
(the earlier N's records kept while the next one runs). Not timed: the latency is
bench/admission.py."""

import numpy as np
import pytest

from svrobs_core import parse_spec, plan_units, run_spec
from svrobs_core.admission import (
    admit,
    cell_entries,
    grid_cost,
    smallest_unit_seconds,
    stored_bytes,
)
from svrobs_core.records import MATRIX_FIELDS
from svrobs_core.workload import (
    WorkloadError,
    _dataset,
    _dims,
    _ill_conditioned,
    estimate_unit,
    plan_under_memory,
    unit_base_bytes,
    unit_fixed_seconds,
)

ALL = ["estimate", "bounds", "gain", "cost", "cost_bound", "sls"]


def _system(n: int, m: int = 1, p: int | None = None) -> dict:
    p = n if p is None else p
    A = (0.5 * np.eye(n) + 0.02 * np.eye(n, k=1)).tolist()
    C = (2.0 * np.eye(n)[:p]).tolist()
    return {"name": f"s{n}x{m}x{p}", "A": A, "B": np.ones((n, m)).tolist(), "C": C}


def _per_n_loop(spec, unit) -> tuple[float, float]:
    """(cpu seconds, peak bytes) of a unit, one N at a time."""
    si = unit["system"]
    n, m, p, orth = _dims(spec, si)
    r0, r1 = unit["reps"]
    limit = spec.reps if spec.mc_reps is None else spec.mc_reps
    mc_rows = max(0, min(r1, limit) - r0)
    ill_data = _ill_conditioned(spec, si)
    ill = "svr" in spec.estimators and ill_data
    cpu, peak, kept = 0.0, 0.0, 0.0
    for N in unit["N"]:
        c, transient, k = _dataset(
            spec, n=n, m=m, p=p, orth=orth, N=[N], R=r1 - r0, mc_rows=mc_rows, ill=ill,
            ill_data=ill_data,
        )  # fmt: skip
        cpu += float(c[0])
        peak = max(peak, kept + float(transient[0]))
        kept += k
    cpu += unit_fixed_seconds(spec, n=n, p=p)
    return cpu, unit_base_bytes(spec, n=n, p=p, orth=orth) + peak


GRIDS = [
    {"stages": ["estimate"], "estimators": ["ols"]},
    {"stages": ["estimate", "bounds"], "bounds_method": "self-normalized"},
    {"stages": ["estimate", "bounds"], "bounds_method": "bootstrap", "boot_reps": 4},
    {"stages": ALL, "mc_reps": 3, "mc_runs": 4, "horizon": 20, "sls": {"T_fir": 4}},
    {"stages": ALL[:4], "reuse_gain": True, "mc_runs": 4, "horizon": 20},
    {"stages": ["estimate"], "estimators": ["svr"], "T0": 40},  # paper-unstable: the QR path
    {"stages": ["estimate"], "reps": 1, "N": list(range(1, 40))},
]
PLANS = [{}, {"max_cells": 30, "target_cells": 12}, {"max_cells": 5, "target_cells": 5}]


@pytest.mark.parametrize("plan", PLANS, ids=["default", "small", "one-rep"])
@pytest.mark.parametrize("over", GRIDS)
def test_closed_form_equals_the_per_unit_sum(over, plan):
    spec = parse_spec(
        {
            "systems": [_system(3), "paper-unstable", _system(2, m=2, p=1)],
            "sigma_w": [0.1, 0.3],
            "N": [5, 20, 50, 300, 7],
            "T0": 11,
            "reps": 7,
            "gamma": [0.05, 0.1],
            "estimators": ["ols", "svr"],
            **over,
        }
    )
    units = plan_units(spec, **plan)
    oracle = [_per_n_loop(spec, u) for u in units]
    grid = grid_cost(spec, **plan)
    assert grid.n_units == len(units)
    assert grid.cpu_seconds == pytest.approx(sum(c for c, _ in oracle), rel=1e-9)
    assert grid.max_unit_seconds == pytest.approx(max(c for c, _ in oracle), rel=1e-9)
    assert abs(grid.peak_unit_bytes - max(b for _, b in oracle)) <= 1
    for u, (c, b) in zip(units, oracle, strict=True):  # the vectorised unit, too
        got = estimate_unit(spec, u)
        assert got.cpu_seconds == pytest.approx(c, rel=1e-9) and abs(got.peak_bytes - b) <= 1


def test_a_huge_grid_is_refused_by_its_cells_before_any_cost():
    # 10^11 cells: expanding or costing it would take minutes; the product of the axes does not
    spec = parse_spec(
        {
            "systems": ["paper-stable"],
            "sigma_w": [1.0],
            "N": {"start": 1, "stop": 100_000},
            "reps": 1_000_000,
        }
    )
    with pytest.raises(WorkloadError) as exc:
        admit(spec, max_cells=2_000_000, max_cpu_seconds=3600)
    err = exc.value
    assert err.kind == "cells" and err.limit == 2_000_000 and err.estimate == spec.n_cells
    assert "2,000,000" in err.message and f"{spec.n_cells:,}" in err.message


def test_the_one_cpu_example_is_refused_naming_N():
    body = {
        "systems": ["paper-stable"],
        "sigma_w": [0.01 * (i + 1) for i in range(10)],
        "N": {"start": 1, "stop": 100_000},
        "reps": 1,
        "estimators": ["ols"],
        "stages": ["estimate"],
    }
    spec = parse_spec(body)
    with pytest.raises(WorkloadError) as exc:
        admit(spec, max_cells=2_000_000, max_cpu_seconds=3600, max_unit_bytes=2**31)
    assert exc.value.kind == "cpu" and exc.value.field == "N"
    assert exc.value.estimate == pytest.approx(grid_cost(spec).cpu_seconds)


def test_stored_entries_are_the_matrices_a_run_returns():
    """The matrix entries counted per cell = those of the records run_spec makes."""
    for stages in (["estimate"], ["estimate", "bounds"], ["estimate", "bounds", "gain"]):
        spec = parse_spec(
            {
                "systems": [_system(3, m=2, p=2)],
                "sigma_w": [0.1],
                "N": [30],
                "reps": 1,
                "estimators": ["ols"],
                "stages": stages,
            }
        )
        recs = [r for batch in run_spec(spec) for r in batch]
        sizes = {
            sum(np.asarray(r[f]).size for f in MATRIX_FIELDS if r.get(f) is not None) for r in recs
        }
        assert sizes == {cell_entries(spec, 0)}, stages


def test_stored_bytes_cap_names_its_limit_and_grows_with_n():
    def spec(n):
        return parse_spec(
            {
                "systems": [_system(n)],
                "sigma_w": [1.0],
                "N": [10, 20],
                "reps": 50,
                "stages": ["estimate", "bounds"],
            }
        )

    small, big = stored_bytes(spec(2)), stored_bytes(spec(20))
    assert big > 10 * small  # 8 bytes per entry: 2 (n^2 + n m) entries per cell
    assert big >= spec(20).n_cells * 8 * 2 * (400 + 20)
    with pytest.raises(WorkloadError) as exc:
        admit(spec(20), max_stored_bytes=big / 2)
    assert exc.value.kind == "stored" and "MB" in exc.value.message
    admit(spec(2), max_stored_bytes=big / 2)  # the small one is admitted


def test_units_are_split_under_the_unit_cpu_cap_and_cover_the_grid():
    spec = parse_spec(
        {
            "systems": [_system(3)],
            "sigma_w": [0.1, 0.2],
            "N": [20, 40, 80],
            "reps": 40,
            "stages": ["estimate", "bounds", "gain"],
        }
    )
    whole = plan_units(spec)
    longest = max(estimate_unit(spec, u).cpu_seconds for u in whole)
    cap = longest / 5
    units = plan_under_memory(spec, max_unit_seconds=cap)
    assert len(units) > len(whole)
    assert all(estimate_unit(spec, u).cpu_seconds <= cap for u in units)
    covered = sorted(
        (u["system"], u["sigma_w"], N, r) for u in units for N in u["N"] for r in range(*u["reps"])
    )
    assert covered == sorted(
        (u["system"], u["sigma_w"], N, r) for u in whole for N in u["N"] for r in range(*u["reps"])
    )
    got, _ = admit(spec, max_unit_seconds=cap)
    assert got == units
    with pytest.raises(WorkloadError) as exc:  # one repetition of the largest N is over it
        admit(spec, max_unit_seconds=smallest_unit_seconds(spec) / 2)
    assert exc.value.kind == "unit_cpu" and "CPU seconds" in exc.value.message
