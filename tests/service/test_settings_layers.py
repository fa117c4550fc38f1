"""Below the front ends nothing reads the settings itself: the store (``service.db``)
and the application layer (``svrobs_lab``) take the values, or a ``Settings``, from
their callers (docs/architecture.md#layers). An import contract cannot say "the
``Settings`` type only", so this reads the modules' syntax trees instead."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("service/db", "svrobs_lab")
READERS = {"get_settings"}  # the cached reader of the environment
MADE = {"Settings"}  # a Settings() reads the environment too


def _modules() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def _name(node: ast.expr) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def settings_reads(source: str) -> list[str]:
    """Where ``source`` imports ``get_settings``, calls it or makes a ``Settings``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom):
            found += [(node.lineno, f"imports {a.name}") for a in node.names if a.name in READERS]
        elif isinstance(node, ast.Call) and _name(node.func) in READERS | MADE:
            found.append((node.lineno, f"calls {_name(node.func)}()"))
    return [f"line {n}: {what}" for n, what in sorted(found)]


def test_the_check_finds_a_read():
    src = "from service.config import get_settings\nx = get_settings().A\ny = config.Settings()\n"
    assert settings_reads(src) == [
        "line 1: imports get_settings",
        "line 2: calls get_settings()",
        "line 3: calls Settings()",
    ]
    assert settings_reads("from service.config import Settings\ndef f(s: Settings): ...\n") == []


def test_the_layers_have_modules():
    assert len(_modules()) > 20


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_settings_read_below_the_front_ends(path):
    found = settings_reads(path.read_text(encoding="utf-8"))
    assert not found, f"{path.relative_to(ROOT)} reads the settings itself: {found}"
