"""The spec form's two directions (service.web.spec_form): every preset, a custom
system, each bounds method and jobs on a dataset survive values -> posted form -> spec
unchanged (the parser's normalised spec is the oracle); ranges, empty and mistyped
fields; a dataset job sends only the fields it takes."""

from __future__ import annotations

import pytest

from service.web import spec_form
from service.web.pages.submit import presets
from svrobs_core import parse_spec
from svrobs_core.spec import SPEC_KEYS
from svrobs_core.spec_fields import SPEC_FIELDS, for_datasets

CUSTOM = {
    "systems": ["paper-stable", {"name": "mine", "A": [[0.5, 0.1], [0, 0.4]], "B": [[1], [0]]}],
    "sigma_w": [0.2],
    "N": [5, 7],
}
OTHERS = [
    CUSTOM,
    {**CUSTOM, "bounds_method": "self-normalized", "S": 2.0, "lambda0": 0.5},
    {**CUSTOM, "bounds_method": "bootstrap", "boot_reps": 20, "boot_sigma_w": "spec"},
    {**CUSTOM, "bounds_method": "bootstrap", "draws": "wishart"},
    {
        **CUSTOM,
        "stages": ["estimate", "bounds", "gain", "cost"],
        "mc_reps": 2,
        "reuse_gain": True,
        "sls": {"T_fir": 12, "C_bound": 3.5},
    },
]


ON_DATASET = {"dataset": 3, "N": [4, 8], "holdout": 2}
DATASET_SPECS = [
    ON_DATASET,
    {**ON_DATASET, "sigma_w": 0.3, "reps": 4, "gamma": [0.05, 0.1], "estimators": ["svr"]},
    {
        **ON_DATASET,
        "sigma_w": "estimate",
        "C": [[1, 0, 0, 0]],
        "state": {"lags": {"y": 2, "u": 1}},
        "sigma_u": 0.5,
        "sigma_v": 0.2,
        "S": 3.0,
        "lambda0": 0.5,
        "stages": ["estimate", "bounds", "gain", "cost", "sls"],
        "sls": {"T_fir": 10, "C_bound": None},
    },
]


def post(values: dict, **edits) -> tuple[dict, dict]:
    form, lists = spec_form.as_posted(values)
    form.update(edits)
    return spec_form.spec_of(form, lambda k: lists.get(k, []))


@pytest.mark.parametrize(
    "spec",
    [p.spec for p in presets().values()] + OTHERS + DATASET_SPECS,
    ids=lambda s: str(s.get("seed", "x")),
)
def test_every_spec_survives_the_form(spec):
    back, errors = post(spec_form.values_of(spec))
    assert errors == {}
    assert parse_spec(back).to_dict() == parse_spec(spec).to_dict()
    assert spec_form.complete(back) == back  # complete: every field, once


def test_ranges_empty_and_mistyped_fields():
    values = spec_form.values_of(CUSTOM)
    edits = {
        "m.sigma_w": "range",
        "r.sigma_w.start": "0.1",
        "r.sigma_w.stop": "0.5",
        "r.sigma_w.step": "0.1",
        "m.N": "range",
        "r.N.start": "10",
        "r.N.stop": "30",
        "r.N.step": "",
        "f.mc_reps": "",
        "f.T0": "",
    }
    spec, errors = post(values, **edits)
    assert errors == {}
    assert spec["sigma_w"] == [0.1, 0.2, 0.3, 0.4, 0.5]  # as typed, not 0.30000000000000004
    assert spec["N"] == {"start": 10, "stop": 30, "step": 1}
    assert spec["mc_reps"] is None and "T0" not in spec  # empty: null if optional, else default
    _, errors = post(
        values,
        **{
            "f.reps": "ten",
            "f.gamma": "0.1, x",
            "f.M": "inf",
            "m.N": "range",
            "r.N.start": "1.5",
            "r.N.stop": "3",
        },
    )
    assert errors == {
        "reps": "'ten' is not an integer (digits 0-9)",
        "gamma[1]": "'x' is not a number (digits 0-9, a point, an exponent)",
        "M": "must be finite",
        "N.start": "'1.5' is not an integer (digits 0-9)",
    }
    # what Python's float() and int() read but a browser's Number() does not
    _, errors = post(values, **{"f.sigma_w": "1_0, \u0661\u0660, \uff10.5", "f.reps": "1_0"})
    assert set(errors) == {"sigma_w[0]", "sigma_w[1]", "sigma_w[2]", "reps"}, errors
    spec, errors = post(values, **{"f.sigma_w": "+0.5, 1e-1, .25", "f.reps": "+3"})
    assert errors == {} and spec["sigma_w"] == [0.5, 0.1, 0.25] and spec["reps"] == 3
    _, errors = post(
        values,
        **{"m.gamma": "range", "r.gamma.start": "1", "r.gamma.stop": "0", "r.gamma.step": "0.1"},
    )
    assert errors == {"gamma.stop": "must be >= start"}


def test_error_paths_belong_to_their_fields():
    got = spec_form.errors_by_field(
        {
            "systems[1].A": "a",
            "N[2]": "b",
            "sls.T_fir": "c",
            "sls": "d",
            "nope": "e",
            "N.start": "f",
        }
    )
    assert got == {
        "systems": [("systems[1].A", "a")],
        "N": [("N[2]", "b"), ("N.start", "f")],
        "sls.T_fir": [("sls.T_fir", "c"), ("sls", "d")],
        "spec": [("nope", "e")],
    }


def test_a_dataset_job_sends_the_fields_it_takes():
    """A chosen dataset: the simulation's fields (systems, the σ_w grid, T0, ...) are
    not sent even when typed, σ_w is the one level of its own field, the bounds
    method's default is the dataset's; choosing none gives a simulated spec again."""
    values = spec_form.values_of(ON_DATASET)
    assert values["dataset"] == "3" and values["bounds_method"] == "self-normalized"
    assert values["dataset_sigma_w"] == "estimate" and values["sigma_w"] == ""
    typed = {"f.T0": "7", "f.sigma_w": "0.5, 1", "f.mc_runs": "5", "f.dataset_sigma_w": "0.25"}
    spec, errors = post(values, **typed)
    assert errors == {}
    taken = {f.name.split(".")[0] for f in SPEC_FIELDS if for_datasets(f)}
    assert set(spec) <= taken | {
        "dataset",
        "sigma_w",
        "holdout",
        "C",
        "state",
        "sigma_v",
        "sigma_u",
    }
    assert spec["sigma_w"] == 0.25 and "T0" not in spec and "systems" not in spec
    assert parse_spec(spec).measured.sigma_w == 0.25
    spec, errors = post(values, **{"f.C": "[[1, 0]", "f.state": ""})
    assert errors["C"].startswith("not valid JSON") and spec["state"] is None
    for bad, said in (("[" * 3000 + "]" * 3000, "nested too deeply"), ("9" * 5000, "digits")):
        spec, errors = post(values, **{"f.C": bad})
        assert said in errors["C"], errors
        _, errors = post(spec_form.values_of(CUSTOM), **{"f.systems_custom": bad})
        assert errors["systems"].startswith("the custom systems are ") and said in errors["systems"]
    simulated, errors = post(values, **{"f.dataset": "", "f.systems": "paper-stable"})
    assert "dataset" not in simulated and not set(simulated) - SPEC_KEYS
    assert simulated["bounds_method"] == "self-normalized"  # as it was chosen


def test_dataset_error_paths_belong_to_the_dataset_fields():
    errors = {"sigma_w": "a", "holdout": "b", "C[0][1]": "c", "T0": "d", "dataset": "e"}
    assert spec_form.errors_by_field(errors, dataset=True) == {
        "dataset_sigma_w": [("sigma_w", "a")],
        "holdout": [("holdout", "b")],
        "C": [("C[0][1]", "c")],
        "spec": [("T0", "d")],  # a field a dataset job does not show
        "dataset": [("dataset", "e")],
    }
    assert spec_form.errors_by_field({"sigma_w": "a", "holdout": "b"}) == {
        "sigma_w": [("sigma_w", "a")],
        "spec": [("holdout", "b")],
    }
