"""The svrobs CLI: admin commands on a real database (through the console-script entry,
so errors are one line and exit status 2). The REST commands are tested against a real
server in tests/client/test_cli.py."""

from __future__ import annotations

import pytest

from service.config import get_settings
from tests.client.cli_helpers import run_cli


@pytest.fixture
def run(capsys):
    return lambda *args: run_cli(capsys, *args)


@pytest.fixture
def own_db(tmp_path, monkeypatch):
    monkeypatch.setenv("SVROBS_DATABASE_URL", f"sqlite:///{tmp_path / 'cli.db'}")
    get_settings.cache_clear()
    yield
    get_settings.cache_clear()


def test_admin_commands(own_db, run):
    assert run("migrate")[0] == 0
    assert run("admin", "create-team", "lab")[0] == 0
    code, out, err = run("admin", "create-user", "lab", "ana@lab.org", "--admin")
    assert code == 0, err
    code, out, err = run("admin", "create-key", "ana@lab.org", "--name", "laptop")
    assert code == 0, err
    key = out.strip()
    assert key.startswith("svr_") and "shown only once" in err
    code, out, _ = run("admin", "list-keys")
    assert key.split("_")[1] in out and key not in out
    assert run("admin", "revoke-key", key.split("_")[1])[0] == 0


def test_admin_where_there_is_no_database_creates_none_and_says_so(own_db, run, tmp_path):
    """``svrobs admin`` run outside the checkout (no such SQLite file), or on a file no
    migration ran on: one line saying which, no file created, no SQL in the message."""
    code, out, err = run("admin", "list-keys")
    assert code == 2 and err.count("\n") == 1 and "no such file" in err
    assert "SVROBS_DATABASE_URL" in err and "SELECT" not in err
    assert not (tmp_path / "cli.db").exists()
    (tmp_path / "cli.db").touch()
    code, out, err = run("admin", "create-team", "lab")
    assert code == 2 and "never migrated" in err and err.count("\n") == 1
    assert run("migrate")[0] == 0 and run("admin", "create-team", "lab")[0] == 0


def test_errors_are_one_line_exit_2(own_db, run, monkeypatch):
    run("migrate")
    run("admin", "create-team", "lab")
    code, out, err = run("admin", "create-team", "lab")
    assert code == 2 and err == "error: team 'lab' already exists\n"
    code, _, err = run("admin", "create-key", "nobody@lab.org")
    assert code == 2 and err.count("\n") == 1
    monkeypatch.setenv("SVROBS_API_KEY", "svr_abcdefgh_x")
    monkeypatch.setenv("SVROBS_URL", "http://127.0.0.1:1")
    code, _, err = run("status")
    assert code == 2 and err.startswith("error: cannot reach") and err.count("\n") == 1
    monkeypatch.delenv("SVROBS_API_KEY")
    monkeypatch.setenv("SVROBS_CONFIG", "/nonexistent/config.json")
    code, _, err = run("status")
    assert code == 2 and "SVROBS_API_KEY" in err
    code, _, err = run("submit", "/nonexistent/spec.json")
    assert code == 2 and err.startswith("error: cannot read")
