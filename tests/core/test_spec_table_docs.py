"""docs/spec.md's table of spec fields and the spec's JSON Schema in OpenAPI both say
what the declared table (svrobs_core.spec_fields.SPEC_FIELDS) says: one row per field,
the same default, unit, one-line meaning, bounds and choices. The oracle for the
schema is the parser: a value the schema refuses, parse_spec refuses too."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from jsonschema_rs import Draft202012Validator  # schemathesis's JSON Schema validator

from svrobs_core.errors import SpecError
from svrobs_core.parsing import parse_spec
from svrobs_core.spec import DATASET_KEYS, SPEC_KEYS
from svrobs_core.spec_fields import REQUIRED, SPEC_FIELDS
from svrobs_lab.schemas import JobSubmit
from svrobs_lab.spec_schema import DATASET_PROPERTIES, spec_properties

DOC = Path(__file__).resolve().parents[2] / "docs" / "spec.md"
TYPES = {  # the docs' words for each kind
    "systems": "list of preset names or [system objects](#system-objects)",
    "numbers": "list of numbers",
    "grid": 'list of integers, or `{"start", "stop", "step"}`',
    "int": "integer",
    "number": "number",
    "choice": "string",
    "choices": "list of strings",
    "bool": "boolean",
}


def doc_rows() -> dict[str, dict[str, str]]:
    """The rows of the table under "## Spec fields", by field name."""
    text = DOC.read_text(encoding="utf-8").split("## Spec fields", 1)[1].split("\n## ", 1)[0]
    lines = [ln for ln in text.splitlines() if ln.startswith("| ")]
    header = [c.strip() for c in lines[0].strip("|").split(" | ")]
    rows = {}
    for ln in lines[1:]:
        cells = [c.strip() for c in ln.strip().strip("|").split(" | ")]
        if set(cells[0]) <= {"-", " "}:
            continue
        assert len(cells) == len(header), ln
        row = dict(zip(header, cells))
        rows[row["field"].strip("`")] = row
    return rows


def _bounds_pattern(f) -> re.Pattern[str]:
    """The declared bounds as the docs write them: ``2 … 10,000``, ``> 0``, ``0 < δ < 1``
    (any symbol for the value)."""
    text = re.escape(f.bounds_text()).replace("x", r"\S+")
    return re.compile(text.replace(re.escape(" … "), " … "))


def test_one_row_per_declared_field():
    rows = doc_rows()
    assert set(rows) == {f.name for f in SPEC_FIELDS} | {"sls"}
    assert {n.split(".")[0] for n in rows} == SPEC_KEYS


@pytest.mark.parametrize("f", SPEC_FIELDS, ids=lambda f: f.name)
def test_row_says_what_the_table_declares(f):
    row = doc_rows()[f.name]
    assert row["meaning"] == f.help
    assert row["unit"] == (f.unit or "—")
    want_type = TYPES[f.kind] + (" or `null`" if f.optional else "")
    assert row["type"] == want_type
    if f.default is REQUIRED:
        assert row["default"] == "required"
    else:
        assert json.loads(row["default"].strip("`")) == f.default
    if f.bounds_text():
        assert _bounds_pattern(f).search(row["allowed values / validation"]), f.bounds_text()
    for choice in f.choices if f.kind in ("choice", "choices") else ():
        assert f"`{json.dumps(choice)}`" in row["allowed values / validation"], choice
    if f.only_with:
        assert f'only with `"{f.only_with}"`' in row["allowed values / validation"]


def test_sls_row_default_is_its_fields():
    row = doc_rows()["sls"]
    assert json.loads(row["default"].strip("`")) == spec_properties()["sls"]["default"]
    assert parse_spec({"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10]}).to_dict()[
        "sls"
    ] == json.loads(row["default"].strip("`"))


def test_openapi_spec_properties_are_the_tables():
    schema = JobSubmit.model_json_schema()
    props = schema["properties"]
    assert set(props) == SPEC_KEYS | DATASET_KEYS | {"name", "tags"}
    assert schema["required"] == ["N"]  # both kinds of job need N; the parser the rest
    for key, want in spec_properties().items():
        got = props[key]
        assert {k: v for k, v in got.items() if k != "default"} == {
            k: v for k, v in want.items() if k != "default"
        }
        assert got.get("default") == want.get("default"), key
    for f in SPEC_FIELDS:
        s = spec_properties()[f.name] if "." not in f.name else None
        if s is not None:
            assert f.help in s["description"] and (f.unit in s["description"])
            assert s.get("default", REQUIRED) == f.default


BASE = {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10]}
DATASET_BASE = {"dataset": 1, "N": [10]}


def _probes(f):
    """Values just inside and outside the declared bounds, and of the wrong type."""
    integer = f.kind in ("int", "grid")
    out = [None, True, "7", [], {}]
    for b in (f.lo, f.hi):
        if b is not None:
            out += [b, b + (1 if integer else 1e-9), b - (1 if integer else 1e-9)]
    return out


@pytest.mark.parametrize("f", [f for f in SPEC_FIELDS if "." not in f.name], ids=lambda f: f.name)
def test_what_the_schema_refuses_the_parser_refuses(f):
    """Each field's schema is never stricter than parse_spec (the parser is the oracle)."""
    validator = Draft202012Validator(spec_properties()[f.name])
    for v in _probes(f):
        value = [v] if f.kind in ("numbers", "grid", "systems", "choices") else v
        if f.kind == "numbers" or f.kind == "grid":
            values = [value, v]
        else:
            values = [value]
        for value in values:
            spec = {**BASE, f.name: value}
            if f.only_with:
                spec["bounds_method"] = f.only_with
            if f.name == "N":
                spec["T0"] = 2
            if validator.is_valid(value):
                continue
            with pytest.raises(SpecError):
                parse_spec(spec)


DATASET_PROBES = {
    "dataset": [0, 1, -1, 1.5, "1", None, True],
    "holdout": [-1, 0, 2**31, 2**31 - 1, 0.5, None],
    "C": [None, [], [[]], [[1.0, 0.0]], [[True]], [1.0], "I", [[1e101]]],
    "sigma_v": [-1.0, 0.0, 1e101, None, "0.1", True],
    "sigma_u": [0.0, -1.0, 1.0, None, 1e101, "1"],
    "state": [
        None,
        {},
        {"lags": {}},
        {"lags": {"y": 0}},
        {"lags": {"y": 1, "u": -1}},
        {"lags": {"y": 1, "z": 1}},
        {"lags": {"y": 51}},
        {"x": 1},
        3,
    ],
    "sigma_w": ["estimate", "guess", -1.0, 0.0, 1.0, [1.0], True, None],
}


@pytest.mark.parametrize("key", sorted(DATASET_PROBES))
def test_dataset_fields_schema_is_never_stricter_than_the_parser(key):
    """The fields of a dataset job (docs/measured.md#spec): what their schema refuses,
    the dataset parser refuses (checks that need no data)."""
    assert set(DATASET_PROPERTIES) == DATASET_KEYS
    validator = Draft202012Validator(spec_properties()[key])
    for value in DATASET_PROBES[key]:
        if validator.is_valid(value):
            continue
        with pytest.raises(SpecError):
            parse_spec({**DATASET_BASE, key: value})
