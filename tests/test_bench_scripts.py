"""Every name a bench script imports from this project exists: a script whose module
moved fails here, in `make test`, not when someone next measures with it. The scripts
are read, not run (some take a database URL or run their measurement at import)."""

from __future__ import annotations

import ast
import importlib
import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PROJECT = {
    "bench",
    "service",
    "svrobs_cli",
    "svrobs_client",
    "svrobs_core",
    "svrobs_lab",
    "tests",
    "worker",
}
SCRIPTS = sorted((ROOT / "bench").glob("*.py"))


def _imports(path: Path) -> list[tuple[str, str | None]]:
    """(module, name) of every absolute import of a project module (name None for
    ``import module``)."""
    found: list[tuple[str, str | None]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module.split(".")[0] in PROJECT:
                found += [(node.module, a.name) for a in node.names]
        elif isinstance(node, ast.Import):
            found += [(a.name, None) for a in node.names if a.name.split(".")[0] in PROJECT]
    return found


def test_there_are_bench_scripts():
    assert len(SCRIPTS) >= 20


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: p.name)
def test_what_a_bench_script_imports_exists(path):
    for module, name in _imports(path):
        mod = importlib.import_module(module)
        if name is not None:
            assert hasattr(mod, name) or importlib.util.find_spec(f"{module}.{name}"), (
                f"{path.name}: `from {module} import {name}`: {module} has no {name}"
            )
