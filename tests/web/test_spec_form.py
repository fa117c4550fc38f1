"""The spec form's two directions (service.web.spec_form): every preset, a custom
system and each bounds method survive values -> posted form -> spec unchanged (the
parser's normalised spec is the oracle); ranges, empty and mistyped fields."""

from __future__ import annotations

import pytest

from service.web import spec_form
from service.web.pages.submit import presets
from svrobs_core import parse_spec

CUSTOM = {
    "systems": ["paper-stable", {"name": "mine", "A": [[0.5, 0.1], [0, 0.4]], "B": [[1], [0]]}],
    "sigma_w": [0.2],
    "N": [5, 7],
}
OTHERS = [
    CUSTOM,
    {**CUSTOM, "bounds_method": "self-normalized", "S": 2.0, "lambda0": 0.5},
    {**CUSTOM, "bounds_method": "bootstrap", "boot_reps": 20, "boot_sigma_w": "spec"},
    {
        **CUSTOM,
        "stages": ["estimate", "bounds", "gain", "cost"],
        "mc_reps": 2,
        "reuse_gain": True,
        "sls": {"T_fir": 12, "C_bound": 3.5},
    },
]


def post(values: dict, **edits) -> tuple[dict, dict]:
    form, lists = spec_form.as_posted(values)
    form.update(edits)
    return spec_form.spec_of(form, lambda k: lists.get(k, []))


@pytest.mark.parametrize(
    "spec", [p.spec for p in presets().values()] + OTHERS, ids=lambda s: str(s.get("seed", "x"))
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
        "reps": "'ten' is not an integer",
        "gamma[1]": "'x' is not a number",
        "M": "must be finite",
        "N.start": "'1.5' is not an integer",
    }
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
