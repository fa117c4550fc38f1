"""A stage brings what it needs (docs/spec.md#stages-and-what-they-need).

`sls` computes the true system's K and norms itself, so with
`["estimate", "bounds", "sls"]` or `["estimate", "bounds", "gain", "sls"]` its
values are the ones the full chain gives for the same cells.
"""

from __future__ import annotations

import pytest

from svrobs_core import parse_spec, run_spec

BASE = {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [20], "estimators": ["ols"], "reps": 1}
FULL = ["estimate", "bounds", "gain", "cost", "sls"]
SLS_FIELDS = ("J_opt", "J_opt_bound", "sls_status")


def records(stages):
    spec = parse_spec({**BASE, "stages": stages, "mc_reps": 0})
    return [r for batch in run_spec(spec) for r in batch]


@pytest.mark.parametrize(
    "stages", [["estimate", "bounds", "sls"], ["estimate", "bounds", "gain", "sls"]]
)
def test_sls_runs_without_the_cost_stage(stages):
    got = records(stages)
    want = records(FULL)
    assert len(got) == len(want) == 1
    assert got[0]["sls_status"] == "optimal" and got[0]["J_opt"] is not None
    for f in SLS_FIELDS:
        assert got[0][f] == want[0][f], f  # the same numbers as with the full chain
    assert "sls" not in got[0]["notes"].split("stages not run: ")[1].split(";")[0]


def test_a_stage_without_its_needs_is_refused_naming_stages():
    from svrobs_core import SpecError

    with pytest.raises(SpecError) as exc:
        parse_spec({**BASE, "stages": ["estimate", "sls"]})
    assert exc.value.field == "stages" and "'bounds'" in exc.value.message
