"""The cost model (svrobs_core.workload) and the memory-capped unit plan.

Not timed: the estimate against measurement is bench/workload.py. Here: the
estimate grows with every size parameter, and plan_units keeps every unit
under a memory cap while covering the grid exactly once (and the records do
not depend on that split)."""

import numpy as np
import pytest

from svrobs_core import parse_spec, plan_units, run_spec
from svrobs_core.admission import admit
from svrobs_core.measured.workload import measured_fixed_bytes
from svrobs_core.planning import unit_cells
from svrobs_core.workload import (
    DataShape,
    WorkloadError,
    estimate_job,
    estimate_unit,
    plan_under_memory,
)

ALL = ["estimate", "bounds", "gain", "cost", "cost_bound", "sls"]


def _system(n: int, m: int = 1, p: int | None = None) -> dict:
    p = n if p is None else p
    A = (0.5 * np.eye(n) + 0.02 * np.eye(n, k=1)).tolist()
    C = (2.0 * np.eye(n)[:p]).tolist()  # not orthogonal: the general-C design path
    return {"name": f"s{n}x{m}x{p}", "A": A, "B": np.ones((n, m)).tolist(), "C": C}


def _spec(**over) -> dict:
    base = {
        "systems": [_system(3)],
        "sigma_w": [0.1],
        "N": [20],
        "T0": 11,
        "reps": 4,
        "gamma": [0.05],
        "estimators": ["ols", "svr"],
        "stages": ALL,
        "mc_runs": 100,
        "horizon": 50,
        "sls": {"T_fir": 10},
    }
    base.update(over)
    return base


SWEEPS = {
    "n": [{"systems": [_system(n)]} for n in (1, 2, 3, 5, 8, 13, 20)],
    "m": [{"systems": [_system(3, m=m)]} for m in (1, 2, 4, 8)],
    "p": [{"systems": [_system(6, p=p)]} for p in (1, 2, 4, 6)],
    "N": [{"N": [N]} for N in (1, 5, 20, 100, 1000, 10_000)],
    "N grid": [{"N": list(range(1, k + 1))} for k in (1, 2, 5, 20)],
    "T0": [{"T0": T0} for T0 in (2, 5, 11, 100, 1000)],
    "reps": [{"reps": r} for r in (1, 2, 10, 100, 5000)],
    "gammas": [{"gamma": [0.01 * (i + 1) for i in range(k)]} for k in (1, 2, 5, 10)],
    "estimators": [
        {"estimators": e} for e in (["ols"], ["ols", "svr"], ["ols", "svr", "shrunk-ols"])
    ],
    "stages": [{"stages": ALL[:k]} for k in range(1, len(ALL) + 1)],
    "mc_runs": [{"mc_runs": r} for r in (2, 10, 100, 10_000, 1_000_000)],
    "mc_reps": [{"mc_reps": r} for r in (0, 1, 2, 4)],
    "horizon": [{"horizon": h} for h in (1, 10, 200, 10_000)],
    "T_fir": [{"sls": {"T_fir": t}} for t in (2, 10, 100, 1000)],
    "boot_reps": [{"bounds_method": "bootstrap", "boot_reps": b} for b in (2, 10, 100, 1000)],
}


@pytest.mark.parametrize("param", sorted(SWEEPS))
def test_estimate_is_monotone_in_each_size_parameter(param):
    costs = [estimate_job(parse_spec(_spec(**over))) for over in SWEEPS[param]]
    cpu = [c.cpu_seconds for c in costs]
    mem = [c.peak_unit_bytes for c in costs]
    assert all(a <= b for a, b in zip(cpu, cpu[1:])), (param, cpu)
    assert all(a <= b for a, b in zip(mem, mem[1:])), (param, mem)
    assert cpu[-1] > cpu[0], (param, cpu)  # and the parameter does count


def test_estimate_is_positive_and_sums_over_units():
    spec = parse_spec(_spec(sigma_w=[0.1, 1.0], N=[5, 10], reps=3))
    units = plan_units(spec)
    job = estimate_job(spec, units)
    each = [estimate_unit(spec, u) for u in units]
    assert job.n_units == len(units)
    assert job.cpu_seconds == pytest.approx(sum(c.cpu_seconds for c in each))
    assert job.peak_unit_bytes == max(c.peak_bytes for c in each)
    assert all(c.cpu_seconds > 0 and c.peak_bytes > 0 for c in each)


def _covered(spec, units) -> list[tuple]:
    return sorted(
        (u["system"], u["sigma_w"], N, r) for u in units for N in u["N"] for r in range(*u["reps"])
    )


@pytest.mark.parametrize("reuse", [False, True])
def test_plan_respects_the_memory_cap_and_covers_the_grid(reuse):
    obj = _spec(
        systems=["paper-stable"],
        N=[50, 400, 2000],
        reps=300,
        T0=30,
        stages=["estimate", "bounds"],
        reuse_gain=reuse,
    )
    spec = parse_spec(obj)
    plain = plan_units(spec)
    assert estimate_job(spec, plain).peak_unit_bytes > 400 * 2**20  # the cap below binds
    cap = 400 * 2**20
    units = plan_under_memory(spec, max_unit_bytes=cap)
    assert len(units) > len(plain)
    assert all(estimate_unit(spec, u).peak_bytes <= cap for u in units)
    assert _covered(spec, units) == _covered(spec, plain)
    assert sum(unit_cells(spec, u) for u in units) == spec.n_cells
    if reuse:  # reuse_gain couples the N values: they stay in one unit
        assert all(u["N"] == [50, 400, 2000] for u in units)


def test_a_cap_below_one_repetition_leaves_single_rep_units_over_it():
    spec = parse_spec(_spec(systems=["paper-stable"], N=[5000], T0=200, reps=3))
    units = plan_under_memory(spec, max_unit_bytes=1)
    assert [u["reps"] for u in units] == [[0, 1], [1, 2], [2, 3]]
    assert estimate_job(spec, units).peak_unit_bytes > 1  # the caller refuses the spec


def test_records_do_not_depend_on_the_memory_split():
    obj = _spec(systems=["paper-stable"], N=[10, 30], reps=6, stages=["estimate", "bounds"])
    spec = parse_spec(obj)
    units = plan_units(spec)
    one = estimate_unit(spec, {**units[0], "reps": [0, 1], "N": [30]}).peak_bytes
    split = plan_under_memory(spec, max_unit_bytes=one)
    assert len(split) > len(units)

    def key(r):
        return (r["N"], r["rep"], r["estimator"], r["gamma"] or 0)

    a = sorted((r for b in run_spec(spec, units=units) for r in b), key=key)
    b = sorted((r for b in run_spec(spec, units=split) for r in b), key=key)
    assert a == b


# -- admission -----------------------------------------
ISSUE_MC = {
    "systems": ["paper-stable"],
    "sigma_w": [0.1],
    "N": [10],
    "reps": 1,
    "estimators": ["ols"],
    "stages": ["estimate", "bounds", "gain", "cost"],
    "mc_reps": 1,
    "mc_runs": 10_000,
    "horizon": 10_000,
}


def test_admit_refuses_a_job_over_the_cpu_limit_naming_the_field():
    spec = parse_spec(ISSUE_MC)
    with pytest.raises(WorkloadError) as exc:
        admit(spec, max_cpu_seconds=2)
    err = exc.value
    assert err.kind == "cpu" and err.limit == 2 and err.estimate > 2
    assert err.field in ("mc_runs", "horizon")
    assert "CPU seconds" in str(err) and "limit of 2 s" in str(err)
    units, job = admit(spec, max_cpu_seconds=10 * err.estimate)  # under a higher limit: planned
    assert job.cpu_seconds == pytest.approx(err.estimate) and units


def test_admit_refuses_a_unit_over_the_memory_limit_naming_the_field():
    spec = parse_spec({**ISSUE_MC, "N": [900_000], "stages": ["estimate"]})
    with pytest.raises(WorkloadError) as exc:
        admit(spec, max_unit_bytes=512 * 2**20)
    err = exc.value
    assert err.kind == "memory" and err.field == "N" and err.estimate > err.limit
    assert "512 MB" in str(err)


def test_admit_plans_under_the_memory_cap():
    spec = parse_spec({**ISSUE_MC, "N": [2000], "reps": 400, "stages": ["estimate", "bounds"]})
    cap = 300 * 2**20
    units, job = admit(spec, max_unit_bytes=cap, max_cpu_seconds=1e6)
    assert len(units) > 1 and job.peak_unit_bytes <= cap


# -- dataset jobs: the cost from the dataset's shape --------------------------------------
def _measured(**over):
    base = {"dataset": 1, "N": [10, 20], "holdout": 2, "reps": 4, "stages": ALL, "sigma_w": 0.1}
    return parse_spec({**base, **over})


DATA = DataShape(n=3, m=1, lengths=(40,) * 24)


@pytest.mark.parametrize(
    "over,data",
    [
        ({"reps": 8}, DATA),
        ({"N": [10, 22]}, DATA),
        ({"gamma": [0.01, 0.05, 0.1]}, DATA),
        ({}, DataShape(n=3, m=1, lengths=(80,) * 24)),
        ({}, DataShape(n=4, m=2, lengths=(40,) * 24)),
        ({"state": {"lags": {"y": 2, "u": 1}}}, DATA),
    ],
)
def test_measured_estimate_grows_with_the_data_and_the_grid(over, data):
    unit = {"system": 0, "sigma_w": 0, "N": [10, 20], "reps": [0, 4]}
    small = estimate_unit(_measured(), unit, data=DATA)
    spec = _measured(**over)
    bigger = estimate_unit(spec, {**unit, "N": list(spec.N), "reps": [0, spec.reps]}, data=data)
    assert bigger.cpu_seconds > small.cpu_seconds
    assert bigger.peak_bytes >= small.peak_bytes


def test_measured_admission_needs_the_shape_and_plans_under_the_cap():
    spec = _measured(reps=40)
    with pytest.raises(ValueError, match="dataset's shape"):
        admit(spec)
    whole, cost = admit(spec, data=DATA)
    assert whole == [{"system": 0, "sigma_w": 0, "N": [10, 20], "reps": [0, 40]}]
    fixed = measured_fixed_bytes(spec, DATA)
    cap = fixed + 3 * 8 * (4 + 3) * 20 * 40 * 10  # about ten repetitions of N = 20
    units, split = admit(spec, data=DATA, max_unit_bytes=cap)
    assert len(units) > 1 and split.peak_unit_bytes <= cap
    cells = sorted((N, r) for u in units for N in u["N"] for r in range(*u["reps"]))
    assert cells == [(N, r) for N in (10, 20) for r in range(40)]  # each once
    assert split.cpu_seconds >= cost.cpu_seconds  # each unit pays its fixed part
    with pytest.raises(WorkloadError) as err:
        admit(spec, data=DATA, max_unit_bytes=fixed // 2)
    assert err.value.kind == "memory" and err.value.field == "sls.T_fir"  # its program
    with pytest.raises(WorkloadError) as err:
        admit(spec, data=DATA, max_cpu_seconds=cost.cpu_seconds / 2)
    assert err.value.kind == "cpu" and err.value.field == "reps"


@pytest.mark.parametrize("N,cheaper", [(40, False), (450, True)])
def test_wishart_resamples_cost_less_only_above_the_noise_dimension(N, cheaper):
    """paper-stable (n = 3, m = 1) with T0 = 11: the noise dimension is 44."""
    boot = {"bounds_method": "bootstrap", "N": [N], "T0": 11}
    rol = estimate_job(parse_spec(_spec(**boot)))
    wis = estimate_job(parse_spec(_spec(**boot, draws="wishart")))
    if cheaper:  # measured on 40 repetitions: 3.9 s of CPU -> 0.9 s (the model: 5.4 -> 1.8 s)
        assert wis.cpu_seconds < rol.cpu_seconds / 2
        assert wis.peak_unit_bytes <= rol.peak_unit_bytes
    else:
        assert wis.cpu_seconds == rol.cpu_seconds
        assert wis.peak_unit_bytes == rol.peak_unit_bytes
