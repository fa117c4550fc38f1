"""A system of a simulation spec from a file (docs/datasets.md#systems-from-files):
an NPZ, MATLAB (v5 or v7.3) or JSON file holding ``A`` and ``B``, optionally ``C``,
``sigma_u`` and ``sigma_v``, becomes the ``{name, A, B, C, sigma_u, sigma_v}`` object
a spec's ``systems`` list takes, checked as the spec checks it."""

from __future__ import annotations

import os
from typing import BinaryIO

import numpy as np

from svrobs_core.errors import SpecError
from svrobs_core.systems import resolve_system

from .. import json_text
from .arrays import numeric
from .mat_format import mat5_variables, mat73_variables
from .npz_format import npz_variables
from .parsed import BadDatasetFile, name_refused, printable
from .reader import FORMAT_NAMES, detect

KEYS = ("A", "B", "C", "sigma_u", "sigma_v")
MAX_SYSTEM_BYTES = 1 << 20


def _variables(stream: BinaryIO, fmt: str) -> dict:
    if fmt == "npz":
        return npz_variables(stream, max_array_bytes=16 * MAX_SYSTEM_BYTES)
    if fmt == "mat":
        return mat5_variables(stream, max_array_bytes=16 * MAX_SYSTEM_BYTES)
    if fmt == "mat73":
        return mat73_variables(stream, max_array_bytes=16 * MAX_SYSTEM_BYTES)[0]
    if fmt == "json":
        try:
            data = json_text.loads(stream.read(MAX_SYSTEM_BYTES + 1).decode("utf-8-sig"))
        except ValueError:  # a UnicodeDecodeError too
            raise BadDatasetFile("not valid JSON (UTF-8)") from None
        if not isinstance(data, dict):
            raise BadDatasetFile('a JSON system is an object {"A": [[...]], "B": [[...]]}')
        return data
    raise BadDatasetFile(f"a system file is NPZ, MATLAB (.mat) or JSON, not {FORMAT_NAMES[fmt]}")


def read_system(stream: BinaryIO, *, filename: str | None = None, name: str | None = None) -> dict:
    """The system object of a file (name: ``name``, else the file name's stem);
    BadDatasetFile naming the variable that is missing or wrong."""
    head = stream.read(1024)
    stream.seek(0)
    if not head:
        raise BadDatasetFile("the file is empty")
    variables = _variables(stream, detect(head, filename))
    unknown = next((k for k in variables if k not in KEYS + ("name",)), None)
    if unknown is not None:
        raise BadDatasetFile(
            f"unknown variable {unknown!r}; expected A, B and optionally C, sigma_u, sigma_v"
        )
    for need in ("A", "B"):
        if need not in variables:
            raise BadDatasetFile(f"no variable {need!r} (a system file holds A, B, optionally C)")
    in_file = variables.get("name")
    if isinstance(in_file, np.ndarray) and in_file.dtype.kind == "U" and in_file.size == 1:
        in_file = str(in_file.reshape(-1)[0])
    stem = os.path.splitext(os.path.basename(filename or ""))[0]
    chosen = name or (in_file if isinstance(in_file, str) else None) or stem or "system"
    if not printable(chosen):
        if name:
            raise SpecError("name", name_refused(chosen))
        raise BadDatasetFile(f"name: {name_refused(chosen)}")
    system: dict = {"name": chosen.strip()[:64] or "system"}
    for key in ("A", "B", "C"):
        if key in variables:
            value = np.atleast_2d(numeric(key, variables[key]))
            if value.ndim != 2:
                raise BadDatasetFile(f"{key}: expected a matrix, got {value.ndim} dimensions")
            system[key] = value.tolist()
    for key in ("sigma_u", "sigma_v"):
        if key in variables:
            value = numeric(key, variables[key])
            if value.size != 1:
                raise BadDatasetFile(f"{key}: expected one number, got shape {value.shape}")
            system[key] = float(value.reshape(-1)[0])
    try:
        resolved = resolve_system(system, field="system")
    except SpecError as exc:
        where = exc.field.removeprefix("system").lstrip(".") or "system"
        if where == "name":
            raise SpecError("name", exc.message) from None
        raise BadDatasetFile(f"{where}: {exc.message}") from None
    return resolved.to_dict()
