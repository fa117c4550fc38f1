"""The spec form of /jobs/new: a spec as the form's values, the form's values as a
spec, and every error beside its field.

Inputs are named ``f.<field>`` (``f.sls.T_fir``); a grid field (σ_w, N, γ) is a list
(``f.N``: ``10, 20, 40``) or, with ``m.<field>`` = ``range``, start/stop/step
(``r.N.start`` …: N stays ``{start, stop, step}``, σ_w and γ are expanded to their
values). The fields come from :data:`svrobs_core.spec_fields.SPEC_FIELDS` and
``DATASET_FIELDS``; an option of a bounds method is sent only with that method. A
dataset chosen in ``f.dataset`` makes the spec a job on measured data
(docs/measured.md#spec): the fields such a job takes are sent (σ_w as one level,
``f.dataset_sigma_w``), the simulation's are not. ``static/specform.js`` applies the
same rules in the browser to keep the JSON view and the fields in sync.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping

from svrobs_core.spec import MAX_GRID
from svrobs_core.spec_fields import (
    DATASET_BOUNDS_METHOD,
    DATASET_FIELDS,
    REQUIRED,
    SPEC_FIELDS,
    SpecField,
    for_datasets,
)
from svrobs_lab import json_text
from svrobs_lab.params import NON_FINITE, is_float_text, is_int_text

GROUPS = (
    ("grid", "The grid"),
    ("estimate", "Estimation"),
    ("stages", "Stages"),
    ("bounds", "Bounds"),
    ("gain", "Observer gain"),
    ("cost", "Cost"),
    ("sls", "SLS"),
)
RANGED = ("sigma_w", "N", "gamma")


def _ordered() -> tuple[SpecField, ...]:
    """The form's fields: the table's, the dataset before the systems, its σ_w level
    after the grid's σ_w, holdout after N, the other dataset fields last in their group."""
    extra = {f.form_key: f for f in DATASET_FIELDS}
    after = {"sigma_w": "dataset_sigma_w", "N": "holdout"}
    out: list[SpecField] = []
    for f in SPEC_FIELDS:
        if f.name == "systems":
            out.append(extra.pop("dataset"))
        out.append(f)
        if f.name in after:
            out.append(extra.pop(after[f.name]))
    return (*out, *extra.values())


FORM_FIELDS = _ordered()
_BY_KEY = {f.form_key: f for f in FORM_FIELDS}


def job_of(f: SpecField) -> str:
    """Which job shows the field: ``simulated``, ``dataset``, or "" for both (the
    dataset choice itself is always shown)."""
    if f.kind == "dataset" or (for_datasets(f) and not f.dataset_only):
        return ""
    return "dataset" if f.dataset_only else "simulated"


def applies(f: SpecField, dataset: bool) -> bool:
    """Whether a job on a dataset (``dataset``) or a simulated job takes the field."""
    return job_of(f) in ("", "dataset" if dataset else "simulated")


def default_of(f: SpecField, dataset: bool):
    """The field's default in a job of that kind."""
    if dataset and f.name == "bounds_method":
        return DATASET_BOUNDS_METHOD
    return f.default


class FormError(ValueError):
    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


def groups() -> list[tuple[str, list[SpecField]]]:
    """(title, fields) of the form's sections, in the table's order."""
    return [(title, [f for f in FORM_FIELDS if f.group == key]) for key, title in GROUPS]


def _text(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float) and v.is_integer() and abs(v) < 1e16:
        return repr(v)
    return str(v)


def _get(spec: dict, name: str):
    if name.startswith("sls."):
        return (spec.get("sls") or {}).get(name[4:], REQUIRED)
    return spec.get(name, REQUIRED)


def values_of(spec: dict) -> dict[str, object]:
    """The form's values of ``spec`` (a field it lacks, or that its kind of job does
    not take, shows its default), keyed by the fields' form keys: text for numbers
    and lists, lists for checkbox groups, True/False for a flag; grid fields also
    ``m.<f>`` and ``r.<f>.start/stop/step``; ``systems_custom``: the JSON of the
    system objects (edited in the JSON view); JSON fields as JSON text."""
    out: dict[str, object] = {}
    dataset = "dataset" in spec
    for f in FORM_FIELDS:
        v = _get(spec, f.name) if applies(f, dataset) else REQUIRED
        if v is REQUIRED:
            v = default_of(f, dataset)
        if f.kind == "json":
            out[f.form_key] = "" if v is None or v is REQUIRED else json.dumps(v)
        elif f.kind == "systems":
            chosen = v if isinstance(v, list) else []
            out[f.name] = [s for s in chosen if isinstance(s, str)]
            custom = [s for s in chosen if not isinstance(s, str)]
            out["systems_custom"] = json.dumps(custom) if custom else ""
        elif f.kind in ("numbers", "grid"):
            out[f"m.{f.name}"] = "list"
            if isinstance(v, dict):
                out[f"m.{f.name}"] = "range"
                for part in ("start", "stop", "step"):
                    out[f"r.{f.name}.{part}"] = _text(v.get(part, 1 if part == "step" else ""))
                out[f.name] = ""
            else:
                out[f.name] = ", ".join(map(_text, v)) if isinstance(v, list) else ""
        elif f.kind == "choices":
            out[f.name] = list(v) if isinstance(v, list) else []
        elif f.kind == "bool":
            out[f.name] = v is True
        else:
            out[f.form_key] = "" if v is REQUIRED else _text(v)
    return out


def _number(token: str, name: str, *, integer: bool = False):
    """A number written in ASCII decimal, as the browser reads it (no ``1_0``, no
    non-ASCII digits: Python's own ``float`` would take both)."""
    token = token.strip()
    plain = token[1:] if token.startswith("+") else token
    if is_int_text(plain):
        return int(plain)
    if integer:
        raise FormError(name, f"{token!r} is not an integer (digits 0-9)")
    if plain.lower().lstrip("-") in NON_FINITE:
        raise FormError(name, "must be finite")
    if not is_float_text(plain):
        raise FormError(name, f"{token!r} is not a number (digits 0-9, a point, an exponent)")
    v = float(plain)
    if not math.isfinite(v):
        raise FormError(name, "must be finite")
    return v


def _tokens(text: str) -> list[str]:
    return [t for t in re.split(r"[,\s;]+", text.strip()) if t]


def _expand(start: float, stop: float, step: float, name: str) -> list[float]:
    """start, start + step, … up to stop (inclusive, to 1e-9 of a step)."""
    if step <= 0:
        raise FormError(f"{name}.step", "must be > 0")
    if stop < start:
        raise FormError(f"{name}.stop", "must be >= start")
    n = math.floor((stop - start) / step + 1e-9) + 1
    if n > MAX_GRID:
        raise FormError(name, f"has more than {MAX_GRID} entries")
    return [float(f"{start + i * step:.12g}") for i in range(n)]


def _grid(f: SpecField, form: Mapping, errors: dict):
    if form.get(f"m.{f.name}") == "range":
        parts = {}
        for part in ("start", "stop", "step"):
            text = str(form.get(f"r.{f.name}.{part}", "") or "").strip()
            if not text and part == "step":
                text = "1"
            if not text:
                errors[f"{f.name}.{part}"] = "is required"
                continue
            try:
                parts[part] = _number(text, f"{f.name}.{part}", integer=f.kind == "grid")
            except FormError as exc:
                errors[exc.field] = exc.message
        if len(parts) < 3:
            return None
        if f.kind == "grid":
            return parts  # N keeps its {start, stop, step}: the parser checks it
        try:
            return _expand(parts["start"], parts["stop"], parts["step"], f.name)
        except FormError as exc:
            errors[exc.field] = exc.message
            return None
    text = str(form.get(f"f.{f.name}", "") or "")
    if not text.strip():
        return None
    out = []
    for i, token in enumerate(_tokens(text)):
        try:
            out.append(_number(token, f"{f.name}[{i}]", integer=f.kind == "grid"))
        except FormError as exc:
            errors[exc.field] = exc.message
    return out


def spec_of(form: Mapping, getlist) -> tuple[dict, dict[str, str]]:
    """The spec the form's values describe and the errors of values that are not even
    of their field's type (``reps: 'ten' is not an integer``). ``form.get(name)`` gives
    a value, ``getlist(name)`` every value of a checkbox group. An empty optional
    field is null; an empty required one is left out (the parser says so)."""
    errors: dict[str, str] = {}
    spec: dict = {}
    dataset = bool(str(form.get("f.dataset", "") or "").strip())
    fallback = DATASET_BOUNDS_METHOD if dataset else "paper"
    method = str(form.get("f.bounds_method", "") or fallback)
    for f in FORM_FIELDS:
        if not applies(f, dataset) or (f.only_with and f.only_with != method):
            continue
        key = f"f.{f.form_key}"
        value = None
        if f.kind == "json":
            text = str(form.get(key, "") or "").strip()
            if not text:
                _put(spec, f.name, None)
                continue
            try:
                value = json_text.loads(text)
            except ValueError as exc:
                errors[f.name] = str(exc)
                continue
        elif f.kind == "systems":
            value = [s for s in getlist(key) if s]
            custom = str(form.get("f.systems_custom", "")).strip()
            if custom:
                try:
                    extra = json_text.loads(custom)
                except ValueError as exc:
                    errors["systems"] = f"the custom systems are {exc}"
                    extra = []
                value += extra if isinstance(extra, list) else [extra]
            value = value or None
        elif f.kind in ("numbers", "grid"):
            value = _grid(f, form, errors)
        elif f.kind == "choices":
            value = [c for c in getlist(key) if c]
        elif f.kind == "bool":
            value = form.get(key) in ("on", "true", "yes", "1")
        else:
            text = str(form.get(key, "")).strip()
            if not text:
                if f.optional:
                    _put(spec, f.name, None)
                continue
            if f.kind == "choice" or (f.kind == "level" and text == "estimate"):
                value = text
            else:
                try:
                    value = _number(text, f.name, integer=f.kind in ("int", "dataset"))
                except FormError as exc:
                    errors[exc.field] = exc.message
                    continue
        if value is not None:
            _put(spec, f.name, value)
    return spec, errors


def _put(spec: dict, name: str, value) -> None:
    if name.startswith("sls."):
        spec.setdefault("sls", {})[name[4:]] = value
    else:
        spec[name] = value


def field_of(path: str, *, dataset: bool = False) -> str:
    """The form field (its form key) an error path belongs to in a simulated job or,
    with ``dataset``, in a job on a dataset: ``N[2]`` -> ``N``, ``sls.T_fir`` ->
    ``sls.T_fir``, ``systems[0].A`` -> ``systems``, ``sigma_w`` of a dataset job ->
    ``dataset_sigma_w``; ``spec`` for a field the form does not show for that job."""
    if path == "sls" or path.startswith("sls."):
        return path if path in ("sls.T_fir", "sls.C_bound") else "sls.T_fir"
    top = path.split("[", 1)[0].split(".", 1)[0]
    if dataset and top == "sigma_w":
        top = "dataset_sigma_w"
    f = _BY_KEY.get(top)
    return top if f is not None and applies(f, dataset) else "spec"


def errors_by_field(
    errors: Mapping[str, str], *, dataset: bool = False
) -> dict[str, list[tuple[str, str]]]:
    """``{field: [(path, message), …]}`` of a flat ``{path: message}``."""
    out: dict[str, list[tuple[str, str]]] = {}
    for path, message in errors.items():
        out.setdefault(field_of(path, dataset=dataset), []).append((path, message))
    return out


def as_posted(values: Mapping[str, object]) -> tuple[dict, dict]:
    """The form :func:`values_of` fills, as the browser would post it: ``(fields,
    checkbox groups)`` for :func:`spec_of`."""
    form: dict[str, object] = {}
    lists: dict[str, list[object]] = {}
    for k, v in values.items():
        key = k if k.startswith(("m.", "r.")) else f"f.{k}"
        if isinstance(v, list):
            lists[key] = v
        elif isinstance(v, bool):
            if v:
                form[key] = "on"
        else:
            form[key] = v
    return form, lists


def complete(spec: dict) -> dict:
    """``spec`` with every field the form shows (its defaults filled in)."""
    form, lists = as_posted(values_of(spec))
    return spec_of(form, lambda k: lists.get(k, []))[0]


def posted_values(form: Mapping, getlist) -> dict[str, object]:
    """The form's values as posted (what was typed, right or wrong), to show again."""
    out: dict[str, object] = {"systems_custom": str(form.get("f.systems_custom", "") or "")}
    for f in FORM_FIELDS:
        key = f"f.{f.form_key}"
        if f.kind in ("systems", "choices"):
            out[f.name] = [v for v in getlist(key) if v]
        elif f.kind == "bool":
            out[f.name] = form.get(key) in ("on", "true", "yes", "1")
        else:
            out[f.form_key] = str(form.get(key, "") or "")
        if f.kind in ("numbers", "grid"):
            out[f"m.{f.name}"] = "range" if form.get(f"m.{f.name}") == "range" else "list"
            for part in ("start", "stop", "step"):
                out[f"r.{f.name}.{part}"] = str(form.get(f"r.{f.name}.{part}", "") or "")
    return out
