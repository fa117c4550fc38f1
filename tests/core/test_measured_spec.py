"""The spec of a job on measured data (docs/measured.md#spec): parse-time and
data-time checks, each naming its field; simulation specs unchanged."""

import numpy as np
import pytest

from svrobs_core import SpecError, parse_spec, plan_units
from svrobs_core.measured import SIGMA_W_ESTIMATED, check_against_data, plan_measured_units

BASE = {"dataset": 4, "N": [5, 10]}


def spec_with(**kw):
    return {**BASE, **kw}


def field_of(obj) -> str:
    with pytest.raises(SpecError) as e:
        parse_spec(obj)
    return e.value.field


def test_defaults_and_round_trip():
    s = parse_spec(BASE)
    opts = s.measured
    assert s.dataset == 4 and s.systems == () and s.sigma_w == ()
    assert opts.holdout == 0 and opts.sigma_w is None and opts.C is None
    assert opts.sigma_v == 0.1 and opts.sigma_u is None and opts.lags is None
    assert s.bounds_method == "self-normalized" and s.S is None and s.lambda0 == 1.0
    assert s.estimators == ("ols", "svr") and s.reps == 45 and s.delta == 0.01
    assert s.n_cells == 2 * 45 * 2
    full = spec_with(
        holdout=3,
        sigma_w=0.5,
        C=[[1.0, 0.0]],
        sigma_v=0.2,
        sigma_u=2.0,
        state={"lags": {"y": 2, "u": 1}},
        gamma=[0.1, 0.2],
        estimators=["ols", "svr", "shrunk-ols"],
        reps=3,
        stages=["estimate", "bounds", "gain"],
        S=3.0,
    )
    s = parse_spec(full)
    assert s.measured.lags == (2, 1) and s.measured.sigma_w == 0.5 and s.measured.C == ((1.0, 0.0),)
    d = s.to_dict()
    assert d["state"] == {"lags": {"y": 2, "u": 1}} and d["sigma_w"] == 0.5 and d["C"] == [[1, 0]]
    assert parse_spec(d) == s and parse_spec(d).to_dict() == d
    assert parse_spec(parse_spec(BASE).to_dict()).to_dict()["sigma_w"] == "estimate"


@pytest.mark.parametrize(
    "obj, field",
    [
        ({**BASE, "systems": ["paper-stable"]}, "dataset"),
        ({"dataset": 4}, "N"),
        (spec_with(dataset=0), "dataset"),
        (spec_with(dataset=True), "dataset"),
        (spec_with(dataset="4"), "dataset"),
        (spec_with(holdout=-1), "holdout"),
        (spec_with(holdout=1.5), "holdout"),
        (spec_with(sigma_w=[0.5]), "sigma_w"),
        (spec_with(sigma_w="0.5"), "sigma_w"),
        (spec_with(sigma_w=-1.0), "sigma_w"),
        (spec_with(C=[[1.0, "a"]]), "C"),
        (spec_with(C=[[1.0, float("nan")]]), "C"),
        (spec_with(sigma_v=-0.1), "sigma_v"),
        (spec_with(sigma_u=0.0), "sigma_u"),
        (spec_with(state="arx"), "state"),
        (spec_with(state={"lags": {"u": 1}}), "state.lags.y"),
        (spec_with(state={"lags": {"y": 0}}), "state.lags.y"),
        (spec_with(state={"lags": {"y": 1, "u": -1}}), "state.lags.u"),
        (spec_with(state={"lags": {"y": 1, "w": 1}}), "state.lags.w"),
        (spec_with(bounds_method="paper"), "bounds_method"),
        (spec_with(bounds_method="bootstrap"), "bounds_method"),
        (spec_with(T0=11), "T0"),
        (spec_with(mc_runs=10), "mc_runs"),
        (spec_with(reuse_gain=True), "reuse_gain"),
        (spec_with(boot_reps=10), "boot_reps"),
        (spec_with(bogus=1), "bogus"),
        (spec_with(N=[0]), "N[0]"),
        (spec_with(gamma=[-1.0]), "gamma[0]"),
        (spec_with(stages=["gain"]), "stages"),
    ],
)
def test_parse_errors_name_the_field(obj, field):
    assert field_of(obj) == field


@pytest.mark.parametrize("key", ["holdout", "C", "sigma_v", "sigma_u", "state"])
def test_simulation_spec_refuses_the_dataset_fields(key):
    obj = {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10], key: 1}
    with pytest.raises(SpecError, match="only used with") as e:
        parse_spec(obj)
    assert e.value.field == key


def test_simulation_specs_keep_their_defaults_and_units():
    s = parse_spec({"systems": ["paper-stable"], "sigma_w": [1.0, 2.0], "N": [10, 20]})
    assert s.measured is None and s.dataset is None and s.bounds_method == "paper"
    assert s.n_cells == 2 * 2 * 45 * 2
    assert "dataset" not in s.to_dict() and "holdout" not in s.to_dict()
    assert len(plan_units(s)) == 2


@pytest.mark.parametrize(
    "obj, shape, field, words",
    [
        (spec_with(holdout=20), (2, 1, 20), "holdout", "below the dataset's 20"),
        (
            spec_with(N=[5, 18], holdout=3),
            (2, 1, 20),
            "N",
            "N = 18 rollouts, but the dataset has 17 for training",
        ),
        (spec_with(N={"start": 5, "stop": 25}), (2, 1, 20), "N", "has 20"),
        (spec_with(C=[[1.0, 0.0, 0.0]]), (2, 1, 20), "C", "2 columns"),
        (spec_with(sigma_v=0.0, C=[[1.0, 0.0]]), (2, 1, 20), "sigma_v", "square invertible"),
        (spec_with(state={"lags": {"y": 2, "u": 1}}), (2, 0, 20), "state.lags.u", "no inputs"),
        (spec_with(state={"lags": {"y": 30, "u": 0}}), (2, 1, 20), "state.lags", "at most 50"),
    ],
)
def test_data_checks_name_the_field(obj, shape, field, words):
    with pytest.raises(SpecError, match=words) as e:
        check_against_data(parse_spec(obj), *shape)
    assert e.value.field == field


def test_layout_and_lag_lengths():
    s = parse_spec(spec_with(state={"lags": {"y": 3, "u": 2}}, sigma_w=0.3))
    lay = check_against_data(s, 2, 1, 20)
    assert (lay.n, lay.m, lay.p, lay.system, lay.sigma_w) == (8, 1, 2, "dataset-4", 0.3)
    np.testing.assert_array_equal(lay.C, np.eye(2, 8))
    assert lay.matrix_shapes["L"] == (8, 2) and lay.matrix_shapes["B_hat"] == (8, 1)
    assert check_against_data(parse_spec(BASE), 3, 0, 20).sigma_w == SIGMA_W_ESTIMATED
    # k0 = max(p - 1, q) = 2: a rollout needs 4 samples (3 transitions)
    with pytest.raises(SpecError, match="rollout 1 has 3 samples") as e:
        check_against_data(s, 2, 1, 20, lengths=[5, 2] + [9] * 18)
    assert e.value.field == "state.lags"
    check_against_data(s, 2, 1, 20, lengths=[3] * 20)


def test_measured_plan_matches_the_grid_and_splits_by_memory():
    s = parse_spec(spec_with(reps=6, estimators=["ols"]))
    units = plan_measured_units(s)
    assert units == plan_units(s) == [{"system": 0, "sigma_w": 0, "N": [5, 10], "reps": [0, 6]}]
    lengths = [10] * 20  # N = 10: 100 samples, d = 3: 8 * (9 + 4) * 100 bytes per repetition
    small = plan_measured_units(s, lengths=lengths, n=2, m=1, max_unit_bytes=2 * 8 * 13 * 100)
    assert [u["reps"] for u in small] == [[0, 2], [2, 4], [4, 6]]
    with pytest.raises(ValueError, match="plan_measured_units"):
        plan_units(s, max_unit_bytes=10**6)
