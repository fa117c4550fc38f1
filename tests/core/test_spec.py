"""Spec and system validation (docs/spec.md#validation-errors): every bad input names its field."""

import math

import numpy as np
import pytest

from svrobs_core import SpecError, parse_spec
from svrobs_core.systems import PRESETS

BASE = {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10]}


def spec_with(**kw):
    d = dict(BASE)
    d.update(kw)
    return d


def custom(**kw):
    s = {"name": "s", "A": [[0.5, 0.0], [0.0, 0.5]], "B": [[1.0], [0.0]]}
    s.update(kw)
    return s


def test_defaults_match_spec_section_10():
    s = parse_spec(BASE)
    assert s.T0 == 11 and s.reps == 45 and s.M == 1.1 and s.delta == 0.01
    assert s.estimators == ("ols", "svr") and s.stages == ("estimate", "bounds")
    assert s.loss_scale == "sum" and s.data == "all" and s.mc_runs == 1000
    assert s.horizon == 200 and s.mc_reps is None and s.margin == 0.01
    assert s.reuse_gain is False and s.gamma_ref == 0.1 and s.seed == 0
    assert s.sls_T_fir == 30 and s.sls_C_bound is None
    sys = s.systems[0]
    np.testing.assert_array_equal(sys.C, np.eye(3))
    assert sys.sigma_u == 1.0 and sys.sigma_v == 0.1


def test_presets_are_the_papers_systems():
    S, U = PRESETS["paper-stable"], PRESETS["paper-unstable"]
    assert np.allclose(np.diag(S["A"]), 0.9) and np.allclose(np.diag(U["A"]), 1.01)
    assert np.allclose(
        np.array(S["A"]) - np.diag(np.diag(S["A"])), np.array(U["A"]) - np.diag(np.diag(U["A"]))
    )
    assert S["B"] == [[1.0], [1.5], [2.0]]
    assert (
        max(abs(np.linalg.eigvals(np.array(U["A"]))))
        > 1
        > max(abs(np.linalg.eigvals(np.array(S["A"]))))
    )


def test_N_range_is_stop_inclusive_and_cells_counted():
    s = parse_spec(spec_with(N={"start": 10, "stop": 450, "step": 10}, gamma=[0.01, 0.1], reps=3))
    assert s.N[0] == 10 and s.N[-1] == 450 and len(s.N) == 45
    assert s.cells_per_rep == 3 and s.n_cells == 45 * 3 * 3


def test_custom_system_and_flat_B_column():
    s = parse_spec(spec_with(systems=[custom(B=[1.0, 2.0], C=[[1.0, 0.0]], sigma_v=0.2)]))
    assert s.systems[0].B.shape == (2, 1) and s.systems[0].p == 1


@pytest.mark.parametrize(
    "changes, field",
    [
        ({"systems": [custom(A=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])]}, "systems[0].A"),
        ({"systems": [custom(B=[[1.0], [0.0], [2.0]])]}, "systems[0].B"),
        ({"systems": [custom(C=[[1.0, 0.0, 0.0]])]}, "systems[0].C"),
        ({"systems": [custom(A=[[math.nan, 0.0], [0.0, 0.5]])]}, "systems[0].A"),
        ({"systems": [custom(B=[[math.inf], [0.0]])]}, "systems[0].B"),
        ({"systems": [custom(sigma_u=0.0)]}, "systems[0].sigma_u"),
        ({"systems": [custom(sigma_u=-1.0)]}, "systems[0].sigma_u"),
        ({"systems": [custom(sigma_v=-0.1)]}, "systems[0].sigma_v"),
        ({"systems": [custom(sigma_v=0.0, C=[[1.0, 0.0]])]}, "systems[0].sigma_v"),
        ({"systems": [custom(sigma_v=0.0, C=[[1.0, 1.0], [1.0, 1.0]])]}, "systems[0].sigma_v"),
        ({"systems": [custom(colour="red")]}, "systems[0].colour"),
        ({"systems": ["paper-wobbly"]}, "systems[0]"),
        ({"systems": []}, "systems"),
        ({"sigma_w": [-1.0]}, "sigma_w[0]"),
        ({"sigma_w": [math.nan]}, "sigma_w[0]"),
        ({"gamma": [0.1, 0.0]}, "gamma[1]"),
        ({"gamma": [-0.5]}, "gamma[0]"),
        ({"N": [10, 0]}, "N[1]"),
        ({"N": {"start": 0, "stop": 10}}, "N.start"),
        ({"N": [10, 10]}, "N"),
        ({"T0": 1}, "T0"),
        ({"reps": 0}, "reps"),
        ({"reps": 2.5}, "reps"),
        ({"estimators": ["ols", "lasso"]}, "estimators[1]"),
        ({"stages": ["estimate", "magic"]}, "stages[1]"),
        ({"stages": ["estimate", "gain"]}, "stages"),
        ({"loss_scale": "median"}, "loss_scale"),
        ({"data": "some"}, "data"),
        ({"delta": 1.5}, "delta"),
        ({"sls": {"T_fir": 1}}, "sls.T_fir"),
        ({"sls": {"horizon": 3}}, "sls.horizon"),
        ({"colour": "red"}, "colour"),
        # strict types, hard caps, field paths
        ({"reps": 3.0}, "reps"),
        ({"reps": True}, "reps"),
        ({"T0": "11"}, "T0"),
        ({"sigma_w": ["0.5"]}, "sigma_w[0]"),
        ({"sigma_w": [True]}, "sigma_w[0]"),
        ({"M": "1.1"}, "M"),
        ({"N": [10.0]}, "N[0]"),
        ({"systems": [custom(A=[["0.5", 0.0], [0.0, 0.5]])]}, "systems[0].A"),
        ({"systems": [custom(B=[[True], [0.0]])]}, "systems[0].B"),
        ({"systems": [custom(A=[[1e308, 0.0], [0.0, 0.5]])]}, "systems[0].A"),
        ({"systems": [custom(sigma_u="1")]}, "systems[0].sigma_u"),
        ({"systems": [custom(sigma_u=1e200)]}, "systems[0].sigma_u"),
        # an integer beyond the double range (JSON integers have no size limit)
        ({"sigma_w": [10**400]}, "sigma_w[0]"),
        ({"M": 10**400}, "M"),
        ({"gamma": [-(10**400)]}, "gamma[0]"),
        ({"systems": [custom(sigma_v=10**400)]}, "systems[0].sigma_v"),
        (
            {"systems": [custom(sigma_v=0.0, C=[[1.0, 0.0], [1.0, 1e-13]])]},
            "systems[0].sigma_v",
        ),  # nearly singular C: refused here, not mid-run
        ({"systems": [custom(A=np.eye(51).tolist(), B=np.ones((51, 1)).tolist())]}, "systems[0].A"),
        ({"N": [100_000_000]}, "N[0]"),
        ({"N": {"start": 1, "stop": 10**8}}, "N.stop"),
        ({"N": [10, 2000], "T0": 10_000}, "N[1]"),
        ({"T0": 10_001}, "T0"),
        ({"reps": 10**7}, "reps"),
        (
            {"stages": ["estimate", "bounds", "gain", "cost"], "mc_runs": 10**6, "horizon": 10**5},
            "mc_runs",
        ),
        ({"sls": {"T_fir": 1001}}, "sls.T_fir"),
        ({"rng": "mt19937"}, "rng"),
        ({"draws": "bartlett"}, "draws"),
        # a name is printable text: no terminal escape, line break or C1 control
        ({"systems": [custom(name="s\x1b[31m")]}, "systems[0].name"),
        ({"systems": [custom(name="a\nb")]}, "systems[0].name"),
        ({"systems": [custom(name="a\x9bb")]}, "systems[0].name"),
        ({"systems": [custom(name="a\u2028b")]}, "systems[0].name"),
    ],
)
def test_bad_input_names_the_field(changes, field):
    with pytest.raises(SpecError) as exc:
        parse_spec(spec_with(**changes))
    assert exc.value.field == field, str(exc.value)


@pytest.mark.parametrize(
    "obj, field, message",
    [
        ({"sigmaw": [1.0]}, "sigmaw", "unknown field (did you mean 'sigma_w'?)"),
        ({"sytems": ["paper-stable"]}, "sytems", "unknown field (did you mean 'systems'?)"),
        ({"gama": [0.1]}, "gama", "unknown field (did you mean 'gamma'?)"),
        ({"datset": 1}, "datset", "unknown field (did you mean 'dataset'?)"),
        ({"bogus": 1}, "bogus", "unknown field"),  # nothing close: no guess
    ],
)
def test_a_misspelt_field_names_the_field_it_is_close_to(obj, field, message):
    """A typo in a field's name (the CLI: ``error: invalid spec: sigmaw: unknown field
    (did you mean 'sigma_w'?)``), in the parser and in the form's every-error check."""
    from svrobs_core.spec_fields import spec_errors

    with pytest.raises(SpecError) as exc:
        parse_spec({**BASE, **obj})
    assert (exc.value.field, exc.value.message) == (field, message)
    assert spec_errors({**BASE, **obj})[field] == message
    with pytest.raises(SpecError) as exc:  # a job on measured data
        parse_spec({"dataset": 1, "N": [5], "holdot": 4})
    assert exc.value.message == "unknown field (did you mean 'holdout'?)"


@pytest.mark.parametrize("missing", ["systems", "sigma_w", "N"])
def test_required_fields(missing):
    d = dict(BASE)
    del d[missing]
    with pytest.raises(SpecError) as exc:
        parse_spec(d)
    assert exc.value.field == missing


def test_nearly_singular_C_with_noise_is_accepted_and_runs():
    """sigma_v > 0 with a nearly singular C is valid: it runs (nulls with notes where needed)."""
    from svrobs_core import run_spec

    obj = spec_with(
        systems=[custom(sigma_v=0.1, C=[[1.0, 0.0], [1.0, 1e-13]])],
        N=[5],
        reps=1,
        stages=["estimate", "bounds", "gain", "cost"],
        mc_runs=5,
        horizon=5,
    )
    records = [r for b in run_spec(parse_spec(obj)) for r in b]
    assert len(records) == 2


def test_not_an_object():
    with pytest.raises(SpecError) as exc:
        parse_spec([1, 2])
    assert exc.value.field == "spec"


def test_to_dict_round_trips():
    s = parse_spec(spec_with(gamma=[0.01, 0.05], stages=["gain", "bounds", "estimate"]))
    again = parse_spec(s.to_dict())
    assert again.to_dict() == s.to_dict()
    assert s.stages == ("estimate", "bounds", "gain")  # canonical order


@pytest.mark.parametrize(
    "key,default,other", [("rng", "pcg64", "sfc64"), ("draws", "rollouts", "wishart")]
)
def test_rng_and_draws_are_normalised_only_when_not_the_default(key, default, other):
    assert key not in parse_spec(spec_with()).to_dict()
    assert parse_spec(spec_with(**{key: default})).to_dict() == parse_spec(spec_with()).to_dict()
    fast = parse_spec(spec_with(**{key: other}))
    assert getattr(fast, key) == other and parse_spec(fast.to_dict()).to_dict()[key] == other
