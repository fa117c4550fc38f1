"""The declared spec table against the parser: every key once, the defaults of the
normalised spec, each bound probed on parse_spec (at the bound and just beyond); and
spec_errors: every error at once, each the parser's own for that fault alone."""

from __future__ import annotations

import itertools
import math

import pytest

from svrobs_core.errors import SpecError
from svrobs_core.parsing import parse_spec
from svrobs_core.spec import SPEC_KEYS
from svrobs_core.spec_fields import FIELDS_BY_NAME, REQUIRED, SPEC_FIELDS, spec_errors

BASE = {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10]}


def with_field(name: str, value) -> dict:
    spec = dict(BASE)
    f = FIELDS_BY_NAME[name]
    if f.only_with:
        spec["bounds_method"] = f.only_with
    if name == "N":
        spec["T0"] = 2  # N's own bound, under T0 · N <= 10,000,000
    if name.startswith("sls."):
        spec["sls"] = {name.split(".")[1]: value}
    else:
        spec[name] = [value] if f.kind in ("numbers", "grid") else value
    return spec


def error_of(spec: dict) -> SpecError | None:
    try:
        parse_spec(spec)
    except SpecError as exc:
        return exc
    return None


def test_every_key_is_declared_once():
    names = [f.name for f in SPEC_FIELDS]
    assert len(names) == len(set(names))
    assert {n.split(".")[0] for n in names} == SPEC_KEYS
    assert all(f.help and len(f.help) < 90 for f in SPEC_FIELDS)


@pytest.mark.parametrize("method", ["paper", "self-normalized", "bootstrap"])
def test_defaults_are_those_of_the_normalised_spec(method):
    spec = parse_spec({**BASE, "bounds_method": method}).to_dict()
    for f in SPEC_FIELDS:
        if f.default is REQUIRED or (f.only_with and f.only_with != method):
            continue
        if f.name == "bounds_method":  # written only for a method other than the default
            assert f.default == "paper" and spec.get("bounds_method", "paper") == method
            continue
        if f.name in ("rng", "draws"):  # written only when not the default
            parsed = parse_spec({**BASE, "bounds_method": method})
            assert f.name not in spec and getattr(parsed, f.name) == f.default
            continue
        got = spec["sls"][f.name[4:]] if f.name.startswith("sls.") else spec[f.name]
        assert got == f.default, f.name


def _beyond(v: float, *, up: bool, integer: bool) -> float:
    if integer:
        return v + 1 if up else v - 1
    return math.nextafter(v, math.inf if up else -math.inf)


BOUNDED = [f for f in SPEC_FIELDS if f.lo is not None or f.hi is not None]


@pytest.mark.parametrize("f", BOUNDED, ids=lambda f: f.name)
def test_declared_bounds_are_the_parsers(f):
    integer = f.kind in ("int", "grid")
    for bound, is_open, up in ((f.lo, f.lo_open, False), (f.hi, f.hi_open, True)):
        if bound is None:
            continue
        bound = int(bound) if integer else float(bound)
        at = error_of(with_field(f.name, bound))
        assert (at is not None) == is_open, (f.name, bound, at)
        if not is_open:
            out = error_of(with_field(f.name, _beyond(bound, up=up, integer=integer)))
            assert out is not None and out.field.split("[")[0] == f.name, (f.name, out)
        if at is not None:
            assert at.field.split("[")[0] == f.name


FAULTS = {
    "sigma_w": [-1.0],
    "reps": 0,
    "gamma": [0.0],
    "T0": 1,
    "estimators": ["ols", "lasso"],
    "M": -1,
    "delta": 1.5,
    "seed": "7",
    "systems": ["paper-stable", {"name": "bad", "A": [[1, 2]], "B": [[1]]}],
}


def test_three_wrong_fields_are_three_errors_each_the_parsers():
    spec = {**BASE, "sigma_w": [-1.0], "reps": 0, "gamma": [0.0]}
    errors = spec_errors(spec)
    assert set(errors) == {"sigma_w[0]", "reps", "gamma[0]"}
    for key in ("sigma_w", "reps", "gamma"):  # the oracle: the parser, one fault at a time
        alone = error_of({**BASE, key: spec[key]})
        assert errors[alone.field] == alone.message


@pytest.mark.parametrize("n", [1, 2, 3])
def test_errors_iff_the_parser_refuses(n):
    for keys in itertools.combinations(FAULTS, n):
        spec = {**BASE, **{k: FAULTS[k] for k in keys}}
        errors = spec_errors(spec)
        assert {e.split("[")[0].split(".")[0] for e in errors} == set(keys), keys
        first = error_of(spec)
        assert first is not None and errors[first.field] == first.message


def test_rules_between_fields_and_valid_specs():
    assert spec_errors(BASE) == {}
    assert spec_errors({**BASE, "T0": 10_000, "N": [1000, 2000]}) == {
        "N[1]": "T0 * N = 20000000 samples per repetition is over 10000000"
    }
    assert spec_errors({**BASE, "N": [1_000_000], "T0": 2}) == {}  # T0 taken into account
    assert spec_errors(
        {
            **BASE,
            "stages": ["estimate", "bounds", "gain", "cost"],
            "mc_runs": 1_000_000,
            "horizon": 1000,
        }
    ) == {"mc_runs": "mc_runs * horizon = 1000000000 is over 100000000 per cell"}
    assert spec_errors({**BASE, "S": 1.0}) == {
        "S": "is only used with bounds_method 'self-normalized'"
    }
    assert spec_errors({"sigma_w": [1.0], "nope": 1}) == {
        "nope": "unknown field",
        "systems": "is required",
        "N": "is required",
    }
    assert spec_errors([1]) == {"spec": "must be a JSON object"}
    measured = {"dataset": 1, "N": [10], "sigma_w": [1.0]}  # a dataset job: its parser's words
    first = error_of(measured)
    assert first is not None and spec_errors(measured) == {first.field: first.message}
    many = {"dataset": "one", "sigma_w": -1, "bounds_method": "bootstrap", "T0": 5, "C": "x"}
    found = spec_errors(many)
    assert set(found) == {"dataset", "sigma_w", "bounds_method", "T0", "C", "N"}, found
    for key in set(many) - {"dataset"}:  # each the parser's own, on a spec otherwise valid
        alone = error_of({"dataset": 1, "N": [1], key: many[key]})
        assert alone is not None and found[alone.field] == alone.message
    assert found["N"] == "is required" and "self-normalized" in found["bounds_method"]
    assert spec_errors({"dataset": 1, "N": [3], "sigma_w": "estimate", "holdout": 2}) == {}
    assert spec_errors({**BASE, "holdout": 2}) == {
        "holdout": 'is only used with "dataset" (a job on measured data)'
    }
