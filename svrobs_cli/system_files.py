"""Systems of a spec file given as files: ``{"file": "plant.mat", "name": "plant"}`` in
``systems`` is replaced, before the spec is sent, by the system the server reads from
that file (``POST /systems/from-file``; docs/datasets.md#systems-from-files)."""

from __future__ import annotations

from pathlib import Path

from svrobs_cli.errors import CliError, plain_message
from svrobs_client import ValidationError


def resolve_system_files(c, spec: dict, base: Path) -> dict:
    """The spec with every ``{"file": PATH, ...}`` of its ``systems`` replaced by the
    system read from that file (a relative PATH is taken from ``base``, the spec
    file's folder; the entry's other keys, such as ``name`` or ``sigma_v``, win)."""
    systems = spec.get("systems")
    if not isinstance(systems, list) or not any(
        isinstance(s, dict) and "file" in s for s in systems
    ):
        return spec
    out = []
    for i, s in enumerate(systems):
        if isinstance(s, dict) and "file" in s:
            path = Path(str(s["file"]))
            path = path if path.is_absolute() else base / path
            if not path.is_file():
                raise CliError(f"systems[{i}].file: cannot read {path}")
            try:
                loaded = c.system_from_file(path, name=s.get("name"))
            except ValidationError as exc:
                raise CliError(f"systems[{i}].file: {path.name}: {plain_message(exc)}") from None
            s = {**loaded, **{k: v for k, v in s.items() if k != "file"}}
        out.append(s)
    return {**spec, "systems": out}
