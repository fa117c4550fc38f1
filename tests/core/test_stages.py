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


@pytest.mark.parametrize(
    "changes, null",
    [
        # T0 = 600 with M = 0.2: the paper's theta_A leaves the double range, r_A is null
        ({"T0": 600, "M": 0.2}, "eps_A"),
        # sigma_u = 1e-200: Theorem 1's B radius is null while the A radius is finite
        (
            {
                "systems": [
                    {
                        "name": "s",
                        "A": [[0.5, 0.1], [0.0, 0.4]],
                        "B": [[1.0], [0.5]],
                        "sigma_u": 1e-200,
                        "sigma_v": 0.1,
                    }
                ],
                "sigma_w": [0.01],
                "N": [100000],
                "gamma": [1e-6],
                "delta": 0.5,
            },
            "eps_B",
        ),
    ],
)
def test_sls_does_not_run_on_a_null_error_bound(changes, null):
    """max(eps_A, eps_B) is null when either is (docs/science.md#8-sls-sub-optimal-observer-j_opt):
    no J_opt, no bound on it, the reason in the notes."""
    spec = parse_spec(
        {
            **BASE,
            "estimators": ["ols", "svr"],
            "gamma": [0.05],
            **changes,
            "stages": ["estimate", "bounds", "sls"],
        }
    )
    recs = [r for batch in run_spec(spec) for r in batch]
    nulls = [r for r in recs if r[null] is None]
    assert nulls, "the case must give a null bound"
    for r in nulls:
        assert r["sls_status"] == "not_run" and r["J_opt"] is None and r["J_opt_bound"] is None
        assert "J_opt: F undefined (eps_A or eps_B is null)" in r["notes"]
