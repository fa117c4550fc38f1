"""The JSON Schema of a spec's fields, from the declared table
(:data:`svrobs_core.spec_fields.SPEC_FIELDS`, docs/spec.md#spec-fields).

It is what ``/openapi.json`` shows for the spec part of ``POST /api/v1/jobs`` (the
``JobSubmit`` body): each field's type, bounds, default, unit and one-line help,
and the fields of a job on measured data (docs/measured.md#spec; their defaults
are :class:`~svrobs_core.measured.spec.DatasetOptions`'). It never accepts less
than :func:`svrobs_core.parse_spec` does (it leaves out the rules between fields,
the options of another bounds method and which fields each kind of job takes,
which the parser checks and names in its 422), so a body the schema refuses the
parser refuses too.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any

from svrobs_core.measured.spec import DatasetOptions
from svrobs_core.spec import MAX_GRID, MAX_STATE_DIM
from svrobs_core.spec_fields import REQUIRED, SPEC_FIELDS, SpecField
from svrobs_core.systems import MAX_DIM, MAX_ENTRY

__all__ = ["field_schema", "spec_properties"]

_NULL = {"type": "null"}
_MATRIX: dict[str, Any] = {
    "type": "array",
    "minItems": 1,
    "maxItems": MAX_DIM,
    "items": {
        "type": "array",
        "minItems": 1,
        "maxItems": MAX_DIM,
        "items": {"type": "number", "minimum": -MAX_ENTRY, "maximum": MAX_ENTRY},
    },
}
SYSTEM_OBJECT = {
    "type": "object",
    "title": "System",
    "description": "x+ = A x + B u + w, y = C x + v (docs/spec.md#system-objects)",
    "properties": {
        "name": {"type": "string", "minLength": 1, "maxLength": 64},
        "A": {**_MATRIX, "description": "n x n"},
        "B": {
            "anyOf": [_MATRIX, {**_MATRIX["items"], "description": "one column"}],
            "description": "n x m",
        },
        "C": {"anyOf": [_MATRIX, _NULL], "description": "p x n; null: the identity"},
        "sigma_u": {"type": "number", "exclusiveMinimum": 0, "maximum": MAX_ENTRY},
        "sigma_v": {"type": "number", "minimum": 0, "maximum": MAX_ENTRY},
    },
    "required": ["name", "A", "B"],
    "additionalProperties": False,
}


def _scalar(f: SpecField, json_type: str) -> dict[str, Any]:
    out: dict[str, Any] = {"type": json_type}
    if f.lo is not None:
        out["exclusiveMinimum" if f.lo_open else "minimum"] = _bound(f.lo, json_type)
    if f.hi is not None:
        out["exclusiveMaximum" if f.hi_open else "maximum"] = _bound(f.hi, json_type)
    return out


def _bound(v: float, json_type: str) -> float | int:
    return int(v) if json_type == "integer" else v


def _list(items: dict[str, Any]) -> dict[str, Any]:
    return {"type": "array", "minItems": 1, "maxItems": MAX_GRID, "items": items}


def _core(f: SpecField) -> dict[str, Any]:
    """The schema of the value alone (no description, default or null)."""
    if f.kind == "systems":
        preset = {"type": "string", "enum": list(f.choices)}
        return _list({"anyOf": [preset, SYSTEM_OBJECT]})
    if f.kind == "numbers":
        return {**_list(_scalar(f, "number")), "uniqueItems": True}
    if f.kind == "grid":
        bounded = _scalar(f, "integer")
        step = {"type": "integer", "minimum": 1}
        grid = {
            "type": "object",
            "title": "Range",
            "description": "start, start + step, ... up to stop (inclusive)",
            "properties": {"start": bounded, "stop": bounded, "step": step},
            "required": ["start", "stop"],
            "additionalProperties": False,
        }
        return {"anyOf": [{**_list(bounded), "uniqueItems": True}, grid]}
    if f.kind == "int":
        return _scalar(f, "integer")
    if f.kind == "number":
        return _scalar(f, "number")
    if f.kind == "choice":
        return {"type": "string", "enum": list(f.choices)}
    if f.kind == "choices":
        return {**_list({"type": "string", "enum": list(f.choices)}), "uniqueItems": True}
    if f.kind == "bool":
        return {"type": "boolean"}
    raise ValueError(f"{f.name}: no JSON Schema for the kind {f.kind!r}")


def _description(f: SpecField) -> str:
    words = [f.help]
    if f.unit:
        words.append(f"Unit: {f.unit}.")
    if f.only_with:
        words.append(f"Only with bounds_method {f.only_with!r}.")
    return " ".join(w if w.endswith(".") else w + "." for w in words)


def field_schema(f: SpecField) -> dict[str, Any]:
    """The JSON Schema of one declared field: its value, null when the field may be
    empty, its description (help, unit, the bounds method it belongs to) and default."""
    core = _core(f)
    out: dict[str, Any] = {"anyOf": [core, _NULL]} if f.optional else dict(core)
    out["title"] = f.name
    out["description"] = _description(f)
    if f.default is not REQUIRED:
        out["default"] = f.default
    return out


_DATASET_DEFAULTS = {f.name: f.default for f in fields(DatasetOptions)}
_LAG = {"type": "integer", "minimum": 0, "maximum": MAX_STATE_DIM}
# the fields only a job on measured data has (docs/measured.md#spec)
DATASET_PROPERTIES: dict[str, dict[str, Any]] = {
    "dataset": {
        "type": "integer",
        "minimum": 1,
        "title": "dataset",
        "description": "A job on measured data: the dataset's id (instead of systems).",
    },
    "holdout": {
        "type": "integer",
        "minimum": 0,
        "maximum": 2**31 - 1,
        "title": "holdout",
        "description": "Dataset job: rollouts set aside for validation. Unit: rollouts.",
        "default": _DATASET_DEFAULTS["holdout"],
    },
    "C": {
        "anyOf": [_MATRIX, _NULL],
        "title": "C",
        "description": "Dataset job: the observer's output matrix (null: the default).",
        "default": _DATASET_DEFAULTS["C"],
    },
    "sigma_v": {
        "type": "number",
        "minimum": 0,
        "maximum": MAX_ENTRY,
        "title": "sigma_v",
        "description": "Dataset job: measurement-noise standard deviation of the observer.",
        "default": _DATASET_DEFAULTS["sigma_v"],
    },
    "sigma_u": {
        "anyOf": [{"type": "number", "exclusiveMinimum": 0, "maximum": MAX_ENTRY}, _NULL],
        "title": "sigma_u",
        "description": "Dataset job: input standard deviation (null: the inputs' RMS).",
        "default": _DATASET_DEFAULTS["sigma_u"],
    },
    "state": {
        "anyOf": [
            {
                "type": "object",
                "properties": {
                    "lags": {
                        "type": "object",
                        "properties": {"y": {**_LAG, "minimum": 1}, "u": _LAG},
                        "required": ["y"],
                        "additionalProperties": False,
                    }
                },
                "required": ["lags"],
                "additionalProperties": False,
            },
            _NULL,
        ],
        "title": "state",
        "description": "Dataset job: the ARX state {lags: {y: p, u: q}} (null: the full state).",
        "default": _DATASET_DEFAULTS["lags"],
    },
}


def _sigma_w(simulated: dict[str, Any]) -> dict[str, Any]:
    """sigma_w: the table's list, or for a dataset job one number or "estimate"."""
    one = {"type": "number", "minimum": 0}
    estimate = {"type": "string", "enum": ["estimate"]}
    core = {k: v for k, v in simulated.items() if k not in ("title", "description")}
    return {
        "anyOf": [core, one, estimate],
        "title": "sigma_w",
        "description": simulated["description"]
        + ' A dataset job: one number or "estimate" (the default there).',
    }


def spec_properties() -> dict[str, dict[str, Any]]:
    """``{spec key: JSON Schema}`` for every key of a spec of either kind; ``sls`` is
    an object of its declared sub-fields (``sls.T_fir``, ...), which may also be null
    or empty."""
    props: dict[str, dict[str, Any]] = {}
    sls: dict[str, dict[str, Any]] = {}
    for f in SPEC_FIELDS:
        if f.name.startswith("sls."):
            sls[f.name[4:]] = field_schema(f)
        else:
            props[f.name] = field_schema(f)
    props["sls"] = {
        "anyOf": [
            {"type": "object", "properties": sls, "additionalProperties": False},
            _NULL,
        ],
        "title": "sls",
        "description": "Options of the SLS stage; null or {} gives the defaults.",
        "default": {k: s.get("default") for k, s in sls.items()},
    }
    props["sigma_w"] = _sigma_w(props["sigma_w"])
    props.update(DATASET_PROPERTIES)
    return props
