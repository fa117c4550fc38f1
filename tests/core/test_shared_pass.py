"""One pass over the data for specs that differ only in the bounds method
(docs/performance.md#one-pass): the records of each spec are, to the byte, the
ones it gives when run on its own."""

import pytest

from svrobs_core import parse_spec, plan_units
from svrobs_core.pipeline import shares_data
from svrobs_core.runner import run_unit_result, run_unit_results

BASE = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.1, 1.0],
    "N": [8, 15, 30],
    "gamma": [0.01, 0.1],
    "estimators": ["ols", "svr", "shrunk-ols"],
    "reps": 3,
    "seed": 11,
}


def lines(spec, units):
    return [line for u in units for line in run_unit_result(spec, u).json_lines()]


@pytest.mark.parametrize(
    "stages", [["estimate", "bounds"], ["estimate", "bounds", "gain", "cost", "cost_bound"]]
)
def test_shared_pass_records_equal_separate_runs(stages):
    extra = {"stages": stages, "horizon": 20, "mc_runs": 10, "mc_reps": 1}
    paper = parse_spec({**BASE, **extra})
    normalized = parse_spec({**BASE, **extra, "bounds_method": "self-normalized"})
    boot = parse_spec(
        {**BASE, **extra, "N": [8, 30], "bounds_method": "bootstrap", "boot_reps": 12}
    )
    units = plan_units(paper, target_cells=1)  # several units, some without N = 8 or 30
    assert len(units) > 4
    together: dict[str, list[str]] = {"paper": [], "sn": [], "boot": []}
    for u in units:
        for name, res in zip(together, run_unit_results([paper, normalized, boot], u)):
            together[name] += res.json_lines()
    assert together["paper"] == lines(paper, units)
    assert together["sn"] == lines(normalized, units)
    assert together["boot"] == lines(boot, plan_units(boot, target_cells=1))
    assert len(together["boot"]) == boot.n_cells


def test_only_specs_that_share_their_data_run_together():
    paper = parse_spec(BASE)
    assert shares_data(paper, parse_spec({**BASE, "bounds_method": "bootstrap"}))
    assert shares_data(paper, parse_spec({**BASE, "N": [30]}))
    for other in ({"seed": 12}, {"gamma": [0.01]}, {"rng": "sfc64"}, {"N": [8, 16]}):
        assert not shares_data(paper, parse_spec({**BASE, **other})), other
    with pytest.raises(ValueError, match="share"):
        run_unit_results([paper, parse_spec({**BASE, "seed": 12})], plan_units(paper)[0])
