"""The svrobs CLI: admin commands on a real database, REST commands against the app
(through the console-script entry, so errors are one line and exit status 2)."""

from __future__ import annotations

import csv
import io
import json

import pytest

from service.config import get_settings
from svrobs_cli import rest as cli
from svrobs_cli.app import app
from tests.service.svc_fakes import run_job_units
from tests.service.svc_helpers import SMALL_SPEC, SMALL_UNITS


@pytest.fixture
def run(capsys):
    def run(*args) -> tuple[int, str, str]:
        try:
            app(list(args))
            code = 0
        except SystemExit as e:
            code = e.code or 0
        out, err = capsys.readouterr()
        return code, out, err

    return run


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
    monkeypatch.setattr(cli, "CONFIG_PATH", cli.Path("/nonexistent/config.json"))
    code, _, err = run("status")
    assert code == 2 and "SVROBS_API_KEY" in err
    code, _, err = run("submit", "/nonexistent/spec.json")
    assert code == 2 and err.startswith("error: cannot read")


@pytest.fixture
def rest(client, make_account, monkeypatch):
    acc = make_account()
    client.headers["Authorization"] = f"Bearer {acc.key}"
    client.base_url = "http://testserver/api/v1"
    real = cli.Api
    monkeypatch.setattr(cli, "Api", lambda *a, **k: real(http=client))
    return acc


def test_submit_status_results_compare(rest, run, session, tmp_path, monkeypatch):
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(SMALL_SPEC))
    code, out, err = run("submit", str(spec_file), "--name", "cli", "--tag", "a")
    assert code == 0, err
    jid = int(out.split()[1])
    run_job_units(session, jid)

    # --wait polls until the job ends; a stand-in worker runs it on the first poll
    def sleep(_):
        from sqlalchemy import select

        from service.db.models import Job

        last = session.scalar(select(Job.id).order_by(Job.id.desc()).limit(1))
        run_job_units(session, last)

    monkeypatch.setattr(cli.time, "sleep", sleep)
    code, out, err = run("submit", str(spec_file), "--wait")
    assert code == 0, err
    assert f"succeeded {SMALL_UNITS}/{SMALL_UNITS}" in out

    code, out, _ = run("status", str(jid))
    assert code == 0 and f"succeeded {SMALL_UNITS}/{SMALL_UNITS}" in out
    code, out, _ = run("status")
    assert code == 0 and "cli" in out
    dest = tmp_path / "r.csv"
    code, _, err = run("results", str(jid), "--format", "csv", "--out", str(dest), "--N", "20")
    assert code == 0, err
    rows = list(csv.DictReader(io.StringIO(dest.read_text())))
    assert len(rows) == 36 and {x["N"] for x in rows} == {"20"}
    code, out, _ = run("results", str(jid), "--format", "jsonl", "--estimator", "ols")
    assert len(out.splitlines()) == 24
    code, out, _ = run("results", str(jid), "--format", "json")
    assert len(json.loads(out)) == 72
    code, out, _ = run("compare", "--jobs", str(jid), "--metric", "rmse_A", "--by", "N", "--json")
    assert code == 0 and len(json.loads(out)["rows"]) == 2
    code, out, _ = run("compare", "--jobs", str(jid), "--metric", "rmse_A", "--by", "N")
    assert code == 0 and "rmse_A" in out
    code, _, err = run("status", "99999")
    assert code == 2 and err == "error: HTTP 404: job 99999 not found\n"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**SMALL_SPEC, "gamma": [-1]}))
    code, _, err = run("submit", str(bad))
    assert code == 2 and "gamma[0]" in err
