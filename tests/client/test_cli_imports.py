"""The REST commands of ``svrobs`` start without the server's modules: a fresh
interpreter that loads the console script and runs ``svrobs --help`` has imported
neither the settings (pydantic-settings) nor the database layer (SQLAlchemy), which
only ``serve``, ``migrate`` and ``admin`` need (docs/performance.md#the-command-line)."""

from __future__ import annotations

import json
import subprocess
import sys

SERVER_ONLY = ("sqlalchemy", "pydantic_settings", "service.config", "celery", "numpy")


def test_the_console_script_loads_no_server_module():
    code = (
        "import json, sys\n"
        "from svrobs_cli.app import app\n"
        "try:\n"
        "    app(['--help'], standalone_mode=False)\n"
        "except SystemExit:\n"
        "    pass\n"
        f"print(json.dumps([m for m in {SERVER_ONLY!r} if m in sys.modules]))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


def test_serve_reads_the_settings_when_it_needs_them(monkeypatch, tmp_path):
    """The settings are imported at first use, and then are the process's own."""
    from service.config import get_settings
    from svrobs_cli import serve

    monkeypatch.setenv("SVROBS_VAR_DIR", str(tmp_path / "state"))
    get_settings.cache_clear()
    try:
        assert serve.var_dir(serve._settings()) == tmp_path / "state"
    finally:
        get_settings.cache_clear()
