"""Every REST command of the ``svrobs`` CLI against a real server (uvicorn + a celery
worker as real processes). The oracle is the API read with plain httpx; errors must be
one line on stderr, exit status 2, and leave no file behind."""

from __future__ import annotations

import json
import os

import httpx
import pytest

from svrobs_cli.errors import plain_field
from svrobs_cli.rest import fmt
from tests.client.cli_helpers import fake_api, run_cli, run_process
from tests.client.test_client import QUICK, SPEC
from tests.client.test_progress_errors import NOT_A_REPORT, URL, _html
from tests.integration.stack import fetch_jsonl, free_port

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]


@pytest.fixture
def run(stack, capsys, monkeypatch):
    """``run(*args) -> (exit status, stdout, stderr)`` of the console-script entry."""
    monkeypatch.setenv("SVROBS_URL", stack.base_url)
    monkeypatch.setenv("SVROBS_API_KEY", stack.key)
    monkeypatch.setenv("SVROBS_CONFIG", os.devnull)

    return lambda *args: run_cli(capsys, *args)


def _table(out: str) -> list[list[str]]:
    """The tab-separated table a command prints to a pipe (header first)."""
    return [line.split("\t") for line in out.splitlines() if "\t" in line]


def _fails(result, message: str) -> None:
    """Exit status 2 and exactly one line on stderr, starting with ``message``."""
    code, out, err = result
    assert code == 2, result
    assert err.startswith(message) and err.count("\n") == 1, err
    assert "Traceback" not in err + out


@pytest.fixture(scope="module")
def spec_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "spec.json"
    path.write_text(json.dumps(SPEC))
    return path


@pytest.fixture(scope="module")
def job_id(stack, spec_file):
    """A job submitted with ``svrobs submit --wait`` (as a real process)."""
    proc = run_process(stack, "submit", spec_file, "--name", "cli", "--tag", "cli", "--wait")
    assert proc.returncode == 0, proc.stderr
    first, last = proc.stdout.splitlines()[0], proc.stdout.splitlines()[-1]
    jid = int(first.split()[1])
    assert first.startswith(f"job {jid} queued (8 cells, ")
    assert last.startswith(f"job {jid} succeeded ") and last.endswith(" units")
    return jid


def test_submit_print_id(stack, spec_file, http):
    """``--print-id``: stdout is the job id alone (for ``job=$(svrobs submit ...)``); the
    submit and final lines go to stderr."""
    proc = run_process(stack, "submit", spec_file, "--name", "pid", "--wait", "--print-id")
    assert proc.returncode == 0, proc.stderr
    jid = int(proc.stdout)
    assert proc.stdout == f"{jid}\n"
    job = http.get(f"/jobs/{jid}").json()
    assert job["name"] == "pid" and job["status"] == "succeeded"
    lines = proc.stderr.splitlines()
    assert lines[0].startswith(f"job {jid} queued") and lines[-1].startswith(f"job {jid} succeeded")
    proc = run_process(stack, "submit", spec_file, "--print-id")  # without --wait
    assert proc.returncode == 0 and http.get(f"/jobs/{int(proc.stdout)}").json()["spec"]


def test_status(run, job_id, http):
    code, out, err = run("status", job_id)
    assert code == 0, err
    total = http.get(f"/jobs/{job_id}").json()["progress"]["total"]
    assert out.splitlines()[0] == f"job {job_id} succeeded {total}/{total} units"
    assert "  name: cli" in out and "  tags: ['cli']" in out
    code, out, _ = run("status", job_id, "--json")
    assert code == 0 and json.loads(out) == http.get(f"/jobs/{job_id}").json()
    code, out, _ = run("status", "--tag", "cli", "--status", "succeeded", "--json")
    api = http.get("/jobs", params={"tag": "cli", "status": "succeeded", "limit": 20}).json()
    assert code == 0 and json.loads(out) == api
    code, out, _ = run("status", "--owner", "me", "--limit", "1")
    newest = http.get("/jobs", params={"limit": 1}).json()
    j = newest["items"][0]
    assert code == 0 and _table(out) == [
        ["id", "name", "status", "progress", "cells", "tags", "created"],
        [
            str(j["id"]),
            fmt(j["name"]),
            j["status"],
            f"{j['progress']['done']}/{j['progress']['total']}",
            str(j["n_cells"]),
            ",".join(j["tags"]),
            j["created_at"][:19],
        ],
    ]
    assert out.splitlines()[-1] == f"1 of {newest['total']} jobs"
    _fails(run("status", 999_999), "error: job 999999 not found")


def test_results(run, job_id, http, tmp_path):
    out_csv = tmp_path / "r.csv"
    code, _, err = run("results", job_id, "--format", "csv", "--out", out_csv, "--N", 20)
    assert code == 0 and err == f"wrote {out_csv}\n"
    api_csv = http.get(f"/jobs/{job_id}/results", params={"format": "csv", "N": 20}).text
    assert out_csv.read_bytes() == api_csv.encode() and api_csv.count("\n") == 5
    code, out, _ = run("results", job_id, "--format", "jsonl", "--estimator", "ols")
    params = {"format": "jsonl", "estimator": "ols"}
    assert code == 0 and out == http.get(f"/jobs/{job_id}/results", params=params).text
    code, out, _ = run("results", job_id, "--format", "jsonl", "--gamma", "null", "--rep", 1)
    assert code == 0 and [json.loads(x) for x in out.splitlines()] == [
        r for r in fetch_jsonl(http, job_id) if r["gamma"] is None and r["rep"] == 1
    ]
    code, out, _ = run("results", job_id, "--format", "json")
    assert code == 0 and json.loads(out) == fetch_jsonl(http, job_id)
    missing = tmp_path / "x.csv"
    _fails(run("results", 999_999, "--out", missing), "error: job 999999 not found")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.csv"]  # no x.csv, no temp file
    _fails(run("results", job_id, "--format", "xml"), "error: --format must be")


def test_results_sort_and_where(run, job_id, http, tmp_path):
    """--sort / --where equal a sort / filter of the JSONL export; a typo is one line and
    leaves no file."""
    exported = fetch_jsonl(http, job_id)
    cut = sorted(r["rmse_A"] for r in exported)[len(exported) // 2]
    code, out, err = run(
        "results", job_id, "--format", "jsonl", "--sort", "-rmse_A", "--where", f"rmse_A_lt={cut}"
    )
    want = sorted((r for r in exported if r["rmse_A"] < cut), key=lambda r: -r["rmse_A"])
    assert code == 0 and 0 < len(want) < len(exported), err
    assert [json.loads(x) for x in out.splitlines()] == want
    code, out, _ = run(
        "results", job_id, "--format", "json", "--sort=N,-rmse_A", "--where", "N_gte=20"
    )
    want = sorted(
        sorted((r for r in exported if r["N"] >= 20), key=lambda r: -r["rmse_A"]),
        key=lambda r: r["N"],
    )
    assert code == 0 and json.loads(out) == want and want
    out_csv = tmp_path / "x.csv"
    for args, message in [
        (("--sort", "-rmse_X"), "error: --sort: 'rmse_X' is not a numeric record field"),
        (("--where", "rmse_A<0.1"), "error: --where takes FIELD_lt=NUMBER"),
        (("--where", "N=10"), "error: --where takes FIELD_lt=NUMBER"),
        (("--where", "rmse_X_lt=1"), "error: --where: unknown range 'rmse_X_lt'"),
        (("--where", "rmse_A_lt=small"), "error: --where: rmse_A_lt must be a number"),
        (("--where", "certified_gt=0"), "error: --where: certified_gt: certified is a yes/no"),
    ]:
        _fails(run("results", job_id, "--out", out_csv, *args), message)
    assert list(tmp_path.iterdir()) == []


def test_share(run, job_id, http):
    """share create prints the link once; it opens without a key until revoked."""
    code, out, err = run("share", "create", job_id, "--days", 3, "--label", "for the review")
    assert code == 0 and out.count("\n") == 1, err
    url = out.strip()
    listed = http.get(f"/jobs/{job_id}/shares").json()
    sid = listed[0]["id"]
    assert err == f"share {sid} of job {job_id}, expires {listed[0]['expires_at']}\n"
    assert url.startswith(http.base_url.scheme + "://") and "/s/" in url
    assert httpx.get(url, timeout=30).status_code == 200
    code, out, _ = run("share", "list", job_id, "--json")
    assert code == 0 and json.loads(out) == listed
    code, out, _ = run("share", "list", job_id)
    assert listed[0]["label"] == "for the review"
    row = [str(sid), "for the review", listed[0]["created_at"], listed[0]["expires_at"], "", "True"]
    assert code == 0 and row in _table(out) and url not in out
    code, out, _ = run("share", "revoke", sid)
    assert code == 0 and out == f"share {sid} revoked\n"
    assert httpx.get(url, timeout=30).status_code == 404
    assert http.get(f"/jobs/{job_id}/shares").json()[0]["live"] is False
    _fails(run("share", "create", 999_999), "error: job 999999 not found\n")
    _fails(run("share", "create", job_id, "--days", 0), "error: days: ")
    _fails(run("share", "revoke", 999_999), "error: share link 999999 not found\n")


def test_summary_and_compare(run, job_id, http):
    code, out, _ = run("summary", job_id, "--json")
    assert code == 0 and json.loads(out) == http.get(f"/jobs/{job_id}/summary").json()
    code, out, err = run("summary", job_id, "--field", "rmse_A", "--field", "g_L")
    assert code == 0 and err == "", err
    groups = http.get(f"/jobs/{job_id}/summary").json()["groups"]
    keys = ["system", "sigma_w", "N", "estimator", "gamma", "count"]
    assert _table(out) == [keys + ["rmse_A mean", "rmse_A std", "g_L mean", "g_L std"]] + [
        [fmt(g[k]) for k in keys]
        + [fmt(g["stats"][f][s]) for f in ("rmse_A", "g_L") for s in ("mean", "std")]
        for g in groups
    ]
    _fails(run("summary", job_id, "--field", "colour"), "error: --field: colour")
    params = {"jobs": str(job_id), "metric": "rmse_B", "by": "N"}
    code, out, _ = run("compare", "--jobs", job_id, "--metric", "rmse_B", "--by", "N", "--json")
    assert code == 0 and json.loads(out) == http.get("/compare", params=params).json()
    code, out, _ = run("compare", "--jobs", job_id, "--metric", "rmse_B", "--by", "N")
    rows = http.get("/compare", params=params).json()["rows"]
    cols = ["job_id", "N", "mean", "std", "count"]
    assert code == 0 and _table(out) == [cols] + [[fmt(r[c]) for c in cols] for r in rows]
    _fails(run("compare", "--jobs", job_id, "--metric", "colour"), "error: metric: must be")


def test_report(run, job_id, http, tmp_path):
    folder = tmp_path / "rep"
    code, out, err = run("report", job_id, "--out", folder)
    assert code == 0, err
    page = http.get(f"/jobs/{job_id}/report").text
    assert (folder / "report.html").read_text() == page
    n = len(list((folder / "figures").iterdir()))
    assert n == page.count("src='data:image/png;base64,") >= 1
    assert out == f"wrote {folder / 'report.html'} and {n} figures in {folder / 'figures'}\n"
    _fails(run("report", 999_999, "--out", tmp_path / "none"), "error: job 999999 not found")
    assert not (tmp_path / "none").exists()


def test_cancel_and_presets(stack, run, job_id, http, tmp_path):
    code, out, _ = run("presets", "list", "--json")
    assert code == 0 and json.loads(out) == http.get("/presets").json()
    code, out, _ = run("presets", "list")
    assert code == 0 and ["paper-stable", "3", "1", "3", "1", "0.1"] in _table(out)
    quick = tmp_path / "quick.json"
    quick.write_text(json.dumps(QUICK))
    stack.stop("worker1", grace=3)
    try:
        code, out, err = run("submit", quick)
        assert code == 0, err
        jid = int(out.split()[1])
        code, out, _ = run("cancel", jid)
        assert code == 0 and out.startswith(f"job {jid} cancelled 0/")
        assert http.get(f"/jobs/{jid}").json()["status"] == "cancelled"
        code, out, err = run("presets", "run", "--scale", "reduced", "--experiment", "E1")
        assert code == 0, err
        pid = int(out.split()[1])
        assert out.startswith(f"job {pid} queued paper-section-6 E1 (reduced)")
        assert http.get(f"/jobs/{pid}").json()["tags"] == ["paper-section-6", "E1"]
        assert run("cancel", pid)[0] == 0
        _fails(run("presets", "run", "--scale", "huge"), "error: scale: ")
    finally:
        stack.start_worker()
    _fails(run("cancel", job_id), f"error: job {job_id} already succeeded")


def test_schedules(run, job_id, http, spec_file):
    code, out, err = run(
        "schedules",
        "create",
        "cli-nightly",
        "--cron",
        "0 2 * * *",
        "--from-job",
        job_id,
        "--timezone",
        "Europe/Berlin",
        "--tag",
        "n",
    )
    assert code == 0, err
    sid = int(out.split()[1])
    api = http.get(f"/schedules/{sid}").json()
    assert api["spec_template"] == http.get(f"/jobs/{job_id}").json()["spec"]
    assert (
        out
        == f"schedule {sid} 'cli-nightly' '0 2 * * *' Europe/Berlin (enabled, next run {api['next_run_at']}) created\n"
    )
    code, out, _ = run("schedules", "list", "--json")
    assert code == 0 and json.loads(out) == http.get("/schedules").json()
    code, out, _ = run("schedules", "list")
    row = [str(sid), "cli-nightly", "0 2 * * *", "Europe/Berlin", "True", api["next_run_at"]]
    row += ["n", "fixed"]
    assert code == 0 and row in _table(out)
    code, out, _ = run("schedules", "show", sid, "--json")
    assert code == 0 and json.loads(out) == api
    code, out, _ = run("schedules", "disable", sid)
    assert code == 0 and out.endswith("(disabled)\n")
    assert http.get(f"/schedules/{sid}").json()["enabled"] is False
    code, out, _ = run("schedules", "enable", sid)
    assert code == 0 and "(enabled, next run " in out
    assert http.get(f"/schedules/{sid}").json()["enabled"] is True
    code, out, _ = run("schedules", "runs", sid, "--json")
    assert code == 0 and json.loads(out) == http.get(f"/schedules/{sid}/runs").json()
    _fails(
        run("schedules", "create", "bad", "--cron", "61 * * * *", "--spec", spec_file),
        "error: cron: ",
    )
    _fails(run("schedules", "create", "x", "--cron", "@daily"), "error: give exactly one of")
    _fails(
        run("schedules", "create", "cli-nightly", "--cron", "@daily", "--spec", spec_file),
        "error: name: the team already has a schedule named 'cli-nightly'",
    )
    code, out, _ = run("schedules", "delete", sid)
    assert code == 0 and out == f"schedule {sid} deleted\n"
    code, out, err = run(
        *("schedules", "create", "cli-fresh", "--cron", "@daily", "--spec", spec_file),
        *("--seed-policy", "due-time"),
    )
    assert code == 0, err
    fresh = int(out.split()[1])
    assert http.get(f"/schedules/{fresh}").json()["seed_policy"] == "due-time"
    code, out, _ = run("schedules", "show", fresh)
    assert code == 0 and "  seed_policy: due-time\n" in out
    assert run("schedules", "delete", fresh)[0] == 0
    _fails(
        run(
            "schedules",
            "create",
            "y",
            "--cron",
            "@daily",
            "--spec",
            spec_file,
            "--seed-policy",
            "x",
        ),
        "error: --seed-policy must be fixed or due-time, not 'x'\n",
    )
    _fails(run("schedules", "show", sid), f"error: schedule {sid} not found")
    # made from a job without --tag: the job's tags (its spec's run again as it was)
    code, out, err = run(
        "schedules", "create", "cli-again", "--cron", "@daily", "--from-job", job_id
    )
    assert code == 0, err
    again = int(out.split()[1])
    assert http.get(f"/schedules/{again}").json()["tags"] == ["cli"]
    assert run("schedules", "delete", again)[0] == 0


def test_delete(stack, run, tmp_path, http):
    quick = tmp_path / "quick.json"
    quick.write_text(json.dumps(QUICK))
    code, out, err = run("submit", quick, "--wait")
    assert code == 0, err
    jid = int(out.split()[1])
    _fails(run("delete", jid), "error: not deleted: give --yes")  # stdin is no terminal
    assert http.get(f"/jobs/{jid}").status_code == 200
    code, out, err = run("delete", jid, "--yes")
    assert code == 0 and out == f"job {jid} deleted\n", err
    assert http.get(f"/jobs/{jid}").status_code == 404
    _fails(run("delete", jid, "--yes"), f"error: job {jid} not found")
    stack.stop("worker1", grace=3)
    try:
        code, out, err = run("submit", quick)
        queued = int(out.split()[1])
        detail = http.delete(f"/jobs/{queued}").json()["detail"]
        _fails(run("delete", queued, "-y"), f"error: {detail}\n")
        assert run("cancel", queued)[0] == 0
        assert run("delete", queued, "-y")[0] == 0
    finally:
        stack.start_worker()


def test_errors_are_one_line(stack, run, spec_file, tmp_path, http, monkeypatch):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**SPEC, "reps": 0}))
    detail = http.post("/jobs", json={**SPEC, "reps": 0}).json()["detail"]
    _fails(run("submit", bad), f"error: invalid spec: reps: {detail}\n")
    _fails(run("submit", tmp_path / "none.json"), "error: cannot read")
    bad.write_text(json.dumps({**SPEC, "N": "100"}))  # pydantic names it "N.list[any]"
    _fails(run("submit", bad), "error: invalid spec: N: ")
    assert "[any]" not in run("submit", bad)[2]
    monkeypatch.setenv("SVROBS_API_KEY", "svr_not-a-key")
    _fails(run("status"), "error: invalid, revoked or expired API key\n")
    monkeypatch.setenv("SVROBS_URL", f"http://127.0.0.1:{free_port()}")
    _fails(run("status"), "error: cannot reach")
    monkeypatch.delenv("SVROBS_API_KEY")
    _fails(run("status"), "error: no API key")
    proc = run_process(stack, "status", 999_999, timeout=60)
    assert proc.returncode == 2 and proc.stderr == "error: job 999999 not found\n"


def _offline(capsys, monkeypatch, handler=None):
    """``run(*args)`` as the ``run`` fixture's, its requests sent to ``handler`` in this
    process (:func:`fake_api`); no server."""
    monkeypatch.setenv("SVROBS_URL", URL)
    monkeypatch.setenv("SVROBS_API_KEY", "svr_k")
    monkeypatch.setenv("SVROBS_CONFIG", os.devnull)
    if handler is not None:
        fake_api(monkeypatch, handler)
    return lambda *args: run_cli(capsys, *args)


def test_command_lines_that_do_not_parse_are_one_line(capsys, monkeypatch):
    """An unknown command or option, a missing argument, a job id that is not a number:
    one line naming it and the help to read, exit status 2 (not click's usage box)."""
    run = _offline(capsys, monkeypatch)
    for args, message in [
        (("status", "abc"), "error: Invalid value for 'job': Input should be a valid integer"),
        (("nosuch",), "error: No such command 'nosuch' (see "),
        (("status", "--bogus"), "error: No such option: --bogus (see "),
        (("results",), "error: Missing argument 'job' (see "),
        (("schedules", "show", "x"), "error: Invalid value for 'schedule': "),
        (("datasets", "upload", "f.csv"), "error: Missing option '--name' (see "),
    ]:
        result = run(*args)
        _fails(result, message)
        assert result[2].endswith(" --help)\n")
    assert run("status", "abc")[2].endswith(" status --help)\n")
    assert run("--help")[0] == 0 and "Usage:" in run("schedules")[1]  # help, as asked


def test_files_that_cannot_be_read_or_written(capsys, monkeypatch, tmp_path):
    """A spec that is not text or not YAML, a folder given as a file, an output path
    under a file or on a folder, an id that is not a number: one line naming it."""

    def api(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/results"):
            return httpx.Response(200, text="N\n10\n", headers={"content-type": "text/csv"})
        return httpx.Response(200, json={"models": [], "excitation": {}, "notes": []})

    run = _offline(capsys, monkeypatch, api)
    binary, yaml, folder = tmp_path / "bin.json", tmp_path / "bad.yaml", tmp_path / "folder"
    binary.write_bytes(b"\xff\xfe{")
    yaml.write_text("a: [1\n")
    folder.mkdir()
    for args, message in [
        (("submit", binary), f"cannot read {binary}: not a text file (not UTF-8)"),
        (
            ("submit", yaml),
            f"{yaml}: not valid YAML: expected ',' or ']', but got '<stream end>' at line 2, "
            "column 1",
        ),
        (("run-local", folder), f"cannot read {folder}: Is a directory"),
        (("datasets", "upload", folder, "--name", "x"), f"cannot read {folder}: a folder"),
        (("systems", "from-file", folder), f"cannot read {folder}: a folder"),
        (
            ("results", 1, "--out", binary / "r.csv"),
            f"cannot write {binary / 'r.csv'}: {binary} is not a folder",
        ),
        (("results", 1, "--out", folder), f"cannot write {folder}: it is a folder"),
        (
            ("validation", 1, "--out", binary / "v.json"),
            f"cannot write {binary / 'v.json'}: {binary} is not a folder",
        ),
        (("compare", "--jobs", "1,abc"), "'abc' is not an id: ids are whole numbers (digits 0-9)"),
    ]:
        _fails(run(*args), f"error: {message}\n")
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["bad.yaml", "bin.json", "folder"]


def test_a_server_that_is_not_the_api_or_a_url_or_key_that_cannot_be(capsys, monkeypatch, tmp_path):
    """SVROBS_URL on a plain web server (an HTML page, a redirect: no empty export
    written as a success, and no page saved as a report), not http(s), or a key no key
    can be: one line saying so."""
    run = _offline(capsys, monkeypatch, _html)
    _fails(
        run("status"),
        f"error: {URL} is not the svrobs API's address: it answered with an HTML page (HTTP 200)\n",
    )
    _fails(
        run("results", 1, "--out", tmp_path / "r.csv"),
        f"error: {URL} is not the svrobs API's address: it answered with a redirect (HTTP 301)"
        " to /api/v1/jobs/1/results/\n",
    )
    _fails(run("report", 1, "--out", tmp_path / "rep"), f"error: {NOT_A_REPORT}\n")
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setenv("SVROBS_URL", "ftp://svrobs.test")
    _fails(
        run("status"), "error: SVROBS_URL: 'ftp://svrobs.test' is not an http:// or https:// URL\n"
    )
    monkeypatch.setenv("SVROBS_URL", URL)
    monkeypatch.setenv("SVROBS_API_KEY", "svr_\u00e9")
    _fails(run("status"), "error: SVROBS_API_KEY: the API key has a space, a line break or")


@pytest.mark.parametrize(
    "field, plain",
    [
        ("N.list[any]", "N"),
        ("N.dict[str,any]", "N"),
        ("gamma.list[float][0]", "gamma[0]"),
        ("sls.dict[str,any].T", "sls.T"),
        ("systems[0].A", "systems[0].A"),
        ("spec_template.N[0]", "spec_template.N[0]"),
        ("Idempotency-Key", "Idempotency-Key"),
        (None, None),
    ],
)
def test_plain_field(field, plain):
    """pydantic's union-branch and validator names are dropped from a field path."""
    assert plain_field(field) == plain


def test_a_validation_whose_eigenvalues_are_beyond_the_double_range_prints(capsys, monkeypatch):
    """lambda_min null (the data's squares out of the double range): ``none`` and the
    note that says why, not a traceback."""
    note = "eigenvalues beyond the double range (null): ..."
    body = {
        "N": 20,
        "models": [{"estimator": "ols", "gamma": None, "validation": None}],
        "excitation": {"lambda_min": None, "cond": 2.02, "N0": 800, "notes": [note]},
        "notes": [],
    }
    run = _offline(capsys, monkeypatch, lambda r: httpx.Response(200, json=body))
    code, out, err = run("validation", "3")
    assert (code, err) == (0, "")
    line = "excitation of the 20 training rollouts (800 transitions): lambda_min none, "
    assert line + "condition number 2.02\n" in out and f"note: {note}" in out


def test_version_prints_the_installed_package_version(capsys):
    from importlib.metadata import version

    assert run_cli(capsys, "--version") == (0, f"svrobs {version('svrobs')}\n", "")
