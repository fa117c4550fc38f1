"""Which progress bar the client draws where, and errors from bodies that are not the
API's JSON (a proxy's HTML page, a Retry-After header), from servers that are not the
API, from connections lost mid-answer, from a URL or key that cannot be one and from
files that cannot be read or written. No server needed (a fake API in process)."""

from __future__ import annotations

import io
import json
import os
import socket
import sys
import types

import httpx
import numpy as np
import pytest

from svrobs_client import (
    Client,
    ConfigError,
    ConnectionFailed,
    NotFound,
    SvrobsError,
    ValidationError,
    errors,
    progress,
)
from tests.client.cli_helpers import fake_api, run_cli

URL = "http://svrobs.test"


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


class ZMQInteractiveShell:  # the class name Jupyter's kernel shell has
    pass


def test_no_bar_when_disabled_or_not_a_terminal(monkeypatch):
    assert isinstance(progress.make_bar(1, 4, "queued", enabled=False), progress.NoBar)
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert not progress.in_notebook()
    assert isinstance(progress.make_bar(1, 4, "queued"), progress.NoBar)


def test_rich_in_a_terminal(monkeypatch):
    monkeypatch.setattr(sys, "stderr", _Tty())
    bar = progress.make_bar(7, 4, "queued")
    try:
        assert isinstance(bar, progress.RichBar)
    finally:
        bar.close()


def test_notebook_prefers_tqdm_then_rich(monkeypatch):
    fake = types.ModuleType("IPython")
    fake.get_ipython = lambda: ZMQInteractiveShell()
    monkeypatch.setitem(sys.modules, "IPython", fake)
    monkeypatch.setattr(sys, "stderr", io.StringIO())  # a kernel's stderr is no terminal
    assert progress.in_notebook()
    monkeypatch.setattr(progress, "_importable", lambda name: name == "tqdm")
    monkeypatch.setattr(progress, "TqdmBar", lambda *a, **k: ("tqdm", a))
    assert progress.make_bar(7, 4, "queued") == ("tqdm", (7, 4, "queued"))
    monkeypatch.setattr(progress, "_importable", lambda name: name == "rich")
    bar = progress.make_bar(7, 4, "queued")
    try:
        assert isinstance(bar, progress.RichBar)
    finally:
        bar.close()
    monkeypatch.setattr(progress, "_importable", lambda name: False)
    assert isinstance(progress.make_bar(7, 4, "queued"), progress.NoBar)


def test_rich_bar_draws_the_units():
    from rich.console import Console

    screen = io.StringIO()
    bar = progress.RichBar(3, 4, "queued", console=Console(file=screen, width=100))
    bar.update(2, 4, "running")
    bar.update(4, 4, "succeeded")
    bar.close()
    assert "job 3 succeeded" in screen.getvalue() and "4/4 units" in screen.getvalue()


def test_errors_from_other_bodies():
    page = b"<html><body><h1>502 Bad Gateway</h1>\n</body></html>"
    err = errors.error_from_response(502, page, {})
    assert type(err) is errors.ServerError and err.status == 502 and err.field is None
    assert err.message == (
        "the server answered HTTP 502 with an HTML page, not the svrobs API's JSON: 502 Bad Gateway"
    )
    err = errors.error_from_response(503, b"Service Unavailable", {"content-type": "text/plain"})
    assert type(err) is errors.Unavailable and err.message == "Service Unavailable"
    err = errors.error_from_response(429, b'{"detail": "slow down", "field": null}', {})
    assert isinstance(err, errors.RateLimited) and err.retry_after is None
    err = errors.error_from_response(429, b'{"detail": "slow down"}', {"retry-after": "12"})
    assert err.retry_after == 12.0 and str(err) == "slow down (HTTP 429)"
    err = errors.error_from_response(418, b"", {})
    assert type(err) is errors.SvrobsError and err.message == "HTTP 418"
    body = b'{"detail": "Input should be a valid list", "field": "N", "errors": [{"field": "N"}]}'
    err = errors.error_from_response(422, body, {})
    assert (
        err.errors == [{"field": "N"}] and str(err) == "N: Input should be a valid list (HTTP 422)"
    )
    with pytest.raises(errors.SvrobsError):
        raise errors.Unavailable("database down", status=503)


PAGE = (
    b"<!DOCTYPE html><html><head><title>Index</title></head><body><h1>Directory</h1></body></html>"
)


NOT_A_REPORT = (
    f"{URL} does not look like svrobs: the report request got HTTP 200 (text/html) "
    "without the X-Svrobs-Report header of an svrobs report"
)


def _html(request: httpx.Request) -> httpx.Response:
    """A plain web server (``python -m http.server``): pages, a 404 page, and a redirect
    from a folder without its slash."""
    html = {"content-type": "text/html"}
    if request.url.path.endswith("/results"):
        return httpx.Response(301, headers={"location": request.url.path + "/"})
    if request.url.path.endswith("/summary"):
        page = b"<html><body><p>Error code: 404</p><p>Message: File not found.</p></body></html>"
        return httpx.Response(404, content=page, headers=html)
    if request.url.path.endswith("/jobs/2"):
        return httpx.Response(200, content=b"ok", headers={"content-type": "text/plain"})
    return httpx.Response(200, content=PAGE, headers=html)


def test_answers_of_a_server_that_is_not_the_api(monkeypatch, tmp_path):
    """An HTML page, a redirect or a body that is not JSON is a SvrobsError naming the URL
    (not a JSONDecodeError, nor an empty export reported as written); so is a page
    without the API's report header where the report is asked for (not saved)."""
    fake_api(monkeypatch, _html)
    with Client(URL, "svr_k") as c:
        with pytest.raises(SvrobsError, match="is not the svrobs API's address") as e:
            c.jobs()
        assert type(e.value) is SvrobsError and e.value.status == 200
        assert e.value.message == (
            f"{URL} is not the svrobs API's address: it answered with an HTML page (HTTP 200)"
        )
        with pytest.raises(SvrobsError, match=r"a body that is not the API's JSON \(text/plain"):
            c.job(2)
        with pytest.raises(
            SvrobsError, match=r"a redirect \(HTTP 301\) to /api/v1/jobs/1/results/"
        ):
            c.download_results(1, tmp_path / "r.csv")
        with pytest.raises(SvrobsError, match="an HTML page"):
            c.download_dataset(1, tmp_path / "d.csv")
        with pytest.raises(NotFound) as e:
            c.summary_json(1)
        assert e.value.message == (
            f"{URL} answered HTTP 404 with an HTML page, not the svrobs API's JSON: "
            "Error code: 404 Message: File not found."
        )
        for ask in (lambda: c.report(1, tmp_path / "rep"), lambda: c.report_html(1)):
            with pytest.raises(SvrobsError) as e:
                ask()
            assert type(e.value) is SvrobsError and e.value.status == 200
            assert e.value.message == NOT_A_REPORT
    assert list(tmp_path.iterdir()) == []


class _Cut(httpx.SyncByteStream):
    """Two lines of records, then the connection is gone."""

    def __iter__(self):
        yield b'{"N": 10}\n{"N": 20}\n{"N'
        raise httpx.ReadError("connection reset by peer")


def test_a_connection_lost_mid_answer(monkeypatch, tmp_path):
    """The server gone mid-results or between two pages of a summary: ConnectionFailed
    saying which, and no file."""

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/results"):  # the API's type for the format asked
            fmt = request.url.params.get("format")
            media = "text/csv" if fmt == "csv" else "application/x-ndjson"
            return httpx.Response(200, stream=_Cut(), headers={"content-type": media})
        if "offset" in request.url.params:
            raise httpx.ConnectError("connection refused")
        body = {"job_id": 1, "groups": [{"N": 10}], "total": 2, "partial": False}
        return httpx.Response(200, json=body)

    fake_api(monkeypatch, handler)
    with Client(URL, "svr_k") as c:
        with pytest.raises(ConnectionFailed, match=f"^lost the connection to {URL}: conn"):
            c.results_records(1)
        with pytest.raises(ConnectionFailed, match="^lost the connection"):
            c.download_results(1, tmp_path / "r.csv")
        with pytest.raises(ConnectionFailed, match=f"^cannot reach {URL}: connection refused"):
            c.summary_json(1)
    assert list(tmp_path.iterdir()) == []


def test_no_server_at_the_url_says_how_to_start_one(monkeypatch):
    """A refused connection (the CLI run before ``make run`` is up) names the URL and
    what to do; a timeout, where a server may be busy, does not say there is none."""
    with socket.socket() as s:  # a port no one listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url = f"http://127.0.0.1:{port}"
    with Client(url, "svr_k") as c:
        with pytest.raises(ConnectionFailed) as refused:
            c.jobs()
        with pytest.raises(ConnectionFailed) as streamed:  # a streamed download
            c.results_records(1)
    for err in (refused, streamed):
        assert err.value.message.startswith(f"cannot reach {url}: ")
        assert err.value.message.endswith(f" ({errors.NO_SERVER_HINT})")
    assert "make run" in errors.NO_SERVER_HINT and "SVROBS_URL" in errors.NO_SERVER_HINT

    def slow(request):
        raise httpx.ReadTimeout("timed out", request=request)

    fake_api(monkeypatch, slow)
    with Client(URL, "svr_k") as c, pytest.raises(ConnectionFailed) as timed_out:
        c.jobs()
    assert timed_out.value.message == f"cannot reach {URL}: timed out"


@pytest.mark.parametrize(
    "url, key, message",
    [
        ("ftp://svrobs.test", "svr_k", "the url argument: 'ftp://svrobs.test' is not an http"),
        ("svrobs.test:8000", "svr_k", "the url argument: 'svrobs.test:8000' is not an http"),
        ("http://[::1", "svr_k", "the url argument: 'http://[::1' is not an http"),
        (URL, "svr_é", "the api_key argument: the API key has a space, a line break or"),
        (URL, "svr_a\nb", "the api_key argument: the API key has a space, a line break or"),
    ],
)
def test_a_url_or_key_that_cannot_be_one(url, key, message):
    with pytest.raises(ConfigError) as e:
        Client(url, key)
    assert e.value.message.startswith(message) and e.value.status is None


@pytest.mark.parametrize("suffix", ["/api/v1", "/api/v1/", "/"])
def test_a_url_given_with_the_apis_prefix_is_the_servers_root(monkeypatch, suffix):
    """SVROBS_URL copied with the API's prefix (``.../api/v1``): the requests go to
    ``/api/v1/...`` once, not ``/api/v1/api/v1/...`` (a bare 404)."""
    job = job_body(1, cells=1, units=1)
    seen = []
    fake_api(monkeypatch, lambda r: seen.append(r.url.path) or httpx.Response(200, json=job))
    with Client(URL + suffix, "svr_k") as c:
        assert c.url == URL and c.job(1).id == 1
    assert seen == ["/api/v1/jobs/1"]


def test_ids_spec_files_and_output_paths_are_named(monkeypatch, tmp_path):
    """An id that is not a number, a spec file that is not JSON and an output path that
    cannot be written: errors that say so, naming the value or the path."""
    csv = {"content-type": "text/csv; charset=utf-8"}
    fake_api(monkeypatch, lambda r: httpx.Response(200, text="N\n10\n", headers=csv))
    (tmp_path / "bin.json").write_bytes(b"\xff\xfe{")
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "folder").mkdir()
    with Client(URL, "svr_k") as c:
        for not_an_id in ("abc", "1_0", "١", " 1"):  # int() would take the last three
            with pytest.raises(ValueError, match=rf"^{not_an_id!r} is not an id: ids are whole"):
                c.job(not_an_id)
        with pytest.raises(ValueError, match=r"bin.json: not a JSON file \(not UTF-8 text\)$"):
            c.submit(tmp_path / "bin.json")
        with pytest.raises(ValueError, match="bad.json: not valid JSON: Expecting property"):
            c.submit(tmp_path / "bad.json")
        with pytest.raises(NotADirectoryError) as e:
            c.download_results(1, tmp_path / "bad.json" / "r.csv")
        assert e.value.strerror == (
            f"cannot write {tmp_path / 'bad.json' / 'r.csv'}: {tmp_path / 'bad.json'} is not a folder"
        )
        with pytest.raises(IsADirectoryError) as e:
            c.download_results(1, tmp_path / "folder")
        assert e.value.strerror == f"cannot write {tmp_path / 'folder'}: it is a folder"
        c.download_results(1, tmp_path / "new" / "r.csv")  # a missing folder is made
    assert (tmp_path / "new" / "r.csv").read_text() == "N\n10\n"
    assert sorted(p.name for p in tmp_path.rglob("*")) == [
        "bad.json",
        "bin.json",
        "folder",
        "new",
        "r.csv",
    ]


def test_a_written_file_has_the_permissions_of_one_written_in_place(tmp_path):
    """The temporary file is private (mkstemp: 0600); the file it becomes has the
    umask's permissions, or keeps those of the file it replaces."""
    import os
    import stat

    from svrobs_client.files import write_atomic, writer

    def mode(p):
        return stat.S_IMODE(p.stat().st_mode)

    old = os.umask(0o022)
    try:
        write_atomic(tmp_path / "new.json", writer(b"{}"))
        assert mode(tmp_path / "new.json") == 0o644
        os.umask(0o077)
        write_atomic(tmp_path / "private.json", writer(b"{}"))
        assert mode(tmp_path / "private.json") == 0o600
        (tmp_path / "kept.csv").write_bytes(b"a")
        (tmp_path / "kept.csv").chmod(0o640)
        write_atomic(tmp_path / "kept.csv", writer(b"b"))
        assert mode(tmp_path / "kept.csv") == 0o640
        assert (tmp_path / "kept.csv").read_bytes() == b"b"
    finally:
        os.umask(old)


def job_body(job_id: int, *, cells: int, units: int) -> dict:
    """A queued job as ``GET /api/v1/jobs/{id}`` gives it."""
    job = {"id": job_id, "name": None, "tags": [], "status": "queued", "n_cells": cells}
    job |= {"progress": {"done": 0, "total": units, "fraction": 0.0}, "owner": None}
    job |= {"spec": {}, "provenance": {}, "error": None, "timings": {}}
    return job | {"created_at": None, "started_at": None, "finished_at": None}


@pytest.mark.parametrize(
    "cells, units, line",
    [(30, 1, "job 3 queued (30 cells, 1 unit)"), (1, 4, "job 3 queued (1 cell, 4 units)")],
)
def test_the_submit_line_counts_in_words(monkeypatch, capsys, tmp_path, cells, units, line):
    """``svrobs submit``'s first line: a count of one is singular."""
    job = job_body(3, cells=cells, units=units)
    fake_api(monkeypatch, lambda r: httpx.Response(202, json=job))
    monkeypatch.setenv("SVROBS_URL", URL)
    monkeypatch.setenv("SVROBS_API_KEY", "svr_k")
    (tmp_path / "spec.json").write_text('{"systems": ["paper-stable"], "sigma_w": [1], "N": [10]}')
    assert run_cli(capsys, "submit", tmp_path / "spec.json") == (0, line + "\n", "")


@pytest.mark.parametrize("print_id", [False, True])
def test_ctrl_c_while_submit_waits_names_the_job_that_keeps_running(
    monkeypatch, capsys, tmp_path, print_id
):
    """Ctrl-C (KeyboardInterrupt) while ``submit --wait`` polls: exit 130, one line that
    the job keeps running and how to follow or cancel it; with ``--print-id`` the id is
    still printed on stdout (``job=$(svrobs submit ... --print-id)``)."""
    job = job_body(8, cells=30, units=3)

    def api(request):
        if request.method == "POST":
            return httpx.Response(202, json=job)
        raise KeyboardInterrupt  # the user's Ctrl-C while the progress is polled

    fake_api(monkeypatch, api)
    monkeypatch.setenv("SVROBS_URL", URL)
    monkeypatch.setenv("SVROBS_API_KEY", "svr_k")
    monkeypatch.setattr("svrobs_client.client.time.sleep", lambda s: None)
    (tmp_path / "spec.json").write_text('{"systems": ["paper-stable"], "sigma_w": [1], "N": [10]}')
    args = ["submit", tmp_path / "spec.json", "--wait"] + (["--print-id"] if print_id else [])
    code, out, err = run_cli(capsys, *args)
    assert code == 130
    assert out == ("8\n" if print_id else "job 8 queued (30 cells, 3 units)\n")
    assert err.endswith(
        "interrupted: job 8 keeps running (svrobs status 8; svrobs cancel 8 stops it)\n"
    )


def test_results_out_dash_is_stdout(monkeypatch, capsys, tmp_path):
    """``svrobs results JOB --out -`` prints the records, as without ``--out``, and
    writes no file named ``-``."""
    csv = {"content-type": "text/csv; charset=utf-8"}
    fake_api(monkeypatch, lambda r: httpx.Response(200, text="N\n10\n", headers=csv))
    monkeypatch.setenv("SVROBS_URL", URL)
    monkeypatch.setenv("SVROBS_API_KEY", "svr_k")
    monkeypatch.chdir(tmp_path)
    assert run_cli(capsys, "results", "1", "--out", "-") == (0, "N\n10\n", "")
    assert list(tmp_path.iterdir()) == []


def test_compare_reads_every_page_of_groups(monkeypatch):
    """A comparison of more groups than one page: every page is asked for (limit,
    then offsets), and the rows are all there, in the API's order."""
    rows = [{"job_id": 1, "N": n, "mean": float(n), "std": 0.0, "count": 1} for n in range(25)]
    asked = []

    def api(request):  # a server whose default page is 7 groups
        q = dict(request.url.params)
        asked.append((q.get("limit"), int(q.get("offset", 0))))
        start, limit = int(q.get("offset", 0)), int(q.get("limit", 7))
        body = {"metric": "rmse_A", "rows": rows[start : start + limit], "total": len(rows)}
        return httpx.Response(200, json=body | {"limit": limit})

    fake_api(monkeypatch, api)
    with Client(URL, "svr_k") as c:
        body = c.compare_json([1], "rmse_A", by="N", page_size=10)
    assert body["rows"] == rows and body["total"] == 25 and body["limit"] == 7  # the first page's
    assert asked == [(None, 0), ("10", 7), ("10", 17)]


def test_a_download_that_is_not_the_apis_writes_nothing(monkeypatch, tmp_path):
    """Results and files from a server that is not the API (plain text, JSON that is no
    job) are a SvrobsError and leave no file, nor a byte on a stream."""
    answer = {}
    fake_api(monkeypatch, lambda r: httpx.Response(200, **answer))
    for body in (
        {"text": "hello world"},
        {"json": {"hello": 1}},
        {"json": [1, 2]},
        {"json": {"id": 3, "progress": [1]}},
    ):
        answer.clear()
        answer.update(body)
        with Client(URL, "svr_k") as c:
            for fmt in ("csv", "jsonl", "json"):
                with pytest.raises(SvrobsError, match="is not the svrobs API's address"):
                    c.download_results(1, tmp_path / f"r.{fmt}", format=fmt)
            with pytest.raises(SvrobsError, match="is not the svrobs API's address"):
                c.download_model(1, "N=10,estimator=ols,rep=0", out=tmp_path / "m.npz")
            if "progress" not in str(body):  # a job whose progress is not an object: kept
                with pytest.raises(SvrobsError, match="not (the|a job of the) svrobs API"):
                    c.submit({"systems": ["paper-stable"]}, wait=False)
            stream = io.StringIO()
            with pytest.raises(SvrobsError):
                c.download_results(1, stream, format="json")
            assert stream.getvalue() == ""
    assert list(tmp_path.iterdir()) == []


def test_json_results_are_streamed_as_one_array(monkeypatch, tmp_path):
    """format="json" writes json.dumps of the records, built a record at a time."""
    records = [{"N": 10, "x": 0.5}, {"N": 20, "x": None}]
    lines = ["".join(json.dumps(r) + "\n" for r in records), ""]
    nd = {"content-type": "application/x-ndjson"}
    fake_api(monkeypatch, lambda r: httpx.Response(200, text=lines.pop(0), headers=nd))
    with Client(URL, "svr_k") as c:
        c.download_results(1, tmp_path / "r.json", format="json")
        c.download_results(1, tmp_path / "empty.json", format="json")
    assert (tmp_path / "r.json").read_text() == json.dumps(records) + "\n"
    assert (tmp_path / "empty.json").read_text() == "[]\n"


def test_a_request_body_is_json_numpy_plain_and_a_nan_named(monkeypatch):
    """NaN and infinity have no JSON: the field is named before any request (httpx's
    "Out of range float values" named none); numpy numbers go as plain numbers; a
    spec's tags that are not a list are sent as they are, for the API to name."""
    sent = []

    def handler(request):
        sent.append(json.loads(request.content))
        return httpx.Response(202, json={"id": 3, "status": "queued"})

    fake_api(monkeypatch, handler)
    with Client(URL, "svr_k") as c:
        with pytest.raises(ValidationError) as exc:
            c.submit({"systems": ["paper-stable"], "sigma_w": [1.0, float("nan")]}, wait=False)
        assert (exc.value.field, exc.value.message) == (
            "sigma_w[1]",
            "must be finite (no NaN or inf)",
        )
        assert sent == []
        with pytest.raises(ValidationError, match="^Idempotency-Key: must be printable ASCII"):
            c.submit({"systems": ["paper-stable"]}, idempotency_key="clé", wait=False)
        c.submit(
            {"N": [np.int64(10)], "sigma_w": np.array([0.5]), "tags": "demo"},
            tags=["x"],
            wait=False,
        )
        c.submit({"tags": ("a",)}, tags=["x"], wait=False)  # a tuple is a list of tags
    assert sent == [{"N": [10], "sigma_w": [0.5], "tags": "demo"}, {"tags": ["a", "x"]}]


def test_a_download_stopped_by_sigterm_leaves_no_file(tmp_path):
    """``svrobs results --out`` ended by SIGTERM (a `timeout`, a job scheduler) removes
    its temporary file (``.r.csv.*.part``), as Ctrl-C does."""
    import http.server
    import signal
    import subprocess
    import threading
    import time

    class Slow(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # a CSV that never ends
            self.send_response(200)
            self.send_header("Content-Type", "text/csv; charset=utf-8")
            self.end_headers()
            try:
                self.wfile.write(b"N\n")
                while True:
                    self.wfile.write(b"10\n" * 1000)
                    self.wfile.flush()
                    time.sleep(0.05)
            except OSError:
                pass

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Slow)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    env = {
        **os.environ,
        "SVROBS_URL": f"http://127.0.0.1:{server.server_address[1]}",
        "SVROBS_API_KEY": "svr_k",
    }
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "svrobs_cli", "results", "1", "--out", str(out / "r.csv")],
        env=env,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 60
        while not (out.exists() and any(out.iterdir())):  # the temporary file is there
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 128 + signal.SIGTERM
    finally:
        proc.kill()
        server.shutdown()
    assert list(out.iterdir()) == []


def test_json_of_another_shape_is_not_the_api(monkeypatch, capsys):
    """A server answering JSON that is not the API's (a list where a page is due, an
    object without the rows): a SvrobsError naming what was expected, and the CLI's
    one line says so, not the missing key."""

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/summary"):
            return httpx.Response(200, json={"groups": 3, "total": 1})
        return httpx.Response(200, json={"hello": "world"})  # no rows, and not a list

    fake_api(monkeypatch, handler)
    with Client(URL, "svr_k") as c:
        for ask, what in [
            (c.jobs, "a page of jobs"),
            (c.datasets, "a page of datasets"),
            (lambda: c.summary_json(1), "a job's summary"),
            (lambda: c.compare_json([1, 2], "rmse_A"), "a comparison"),
            (lambda: c.shares(1), "a list of links"),
            (c.schedules, "a list of schedules"),
            (lambda: c.schedule_runs(1), "a list of runs"),
            (c.presets, "a list of presets"),
        ]:
            with pytest.raises(SvrobsError, match=f"^the answer is not {what} of the svrobs API"):
                ask()
    monkeypatch.setenv("SVROBS_URL", URL)
    monkeypatch.setenv("SVROBS_API_KEY", "svr_k")
    code, out, err = run_cli(capsys, "status")
    assert code != 0 and out == ""
    assert err.strip().endswith(
        "the answer is not a page of jobs of the svrobs API (is SVROBS_URL its address?)"
    )
