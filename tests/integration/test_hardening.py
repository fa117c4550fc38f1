"""Report builds, sign-out and failed-authentication throttling through real API
processes (embedded stack, and PostgreSQL when the SVROBS_TEST_* URLs are set), with
no worker: submitted jobs stay queued, so their reports are rebuilt as a running
job's would be.

* Twenty concurrent report requests of one team for one job build it once; the
  ones over the team's waiting bound get 429 with Retry-After; another team's
  GET /jobs meanwhile all answer 200. A third job's build while the team builds two
  is a 429.
* Signing out through one API process ends the session for a copied cookie at
  another process too (the sign-in is kept in the database).
* 300 bad bearer keys from one address: the first 10 are 401, the rest 429 (but
  for the tokens that come back while they are sent), and a valid key from that
  address is refused too until Retry-After has passed.

Run with ``-s`` to see the figures.
"""

from __future__ import annotations

import math
import re
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

from tests.service.svc_helpers import TINY_SPEC

from .conftest import _stack_params
from .stack import API, Stack, free_port, submit

pytestmark = [pytest.mark.integration, pytest.mark.timeout(600)]

BUILT = "built the report of job"
STARTED = "building the report of job"
# the API (as svrobs serve runs it) with every report build 3 s longer
SLOW_API = """
import sys, time
import uvicorn
import svrobs_lab.reports as reports
from service.http.request_deadlines import PROTOCOL
render = reports._render
def slow(job, cols):
    time.sleep(3)
    return render(job, cols)
reports._render = slow
uvicorn.run("service.app:app", host="127.0.0.1", port=int(sys.argv[1]), access_log=False,
            http=PROTOCOL)
"""


@pytest.fixture(scope="module", params=_stack_params())
def lab(request, tmp_path_factory):
    """A migrated stack with the API and no worker; ``lab.other_key``: another team's."""
    st = Stack(request.param, tmp_path_factory.mktemp(f"hard-{request.param}"))
    try:
        st.setup()
        st.other_key = st.team_key("other")
        st.start_api(env={"SVROBS_SECRET_KEY": "it-secret-0123456789abcdef"})
        yield st
    finally:
        st.teardown()


def _log(st: Stack, name: str = "api") -> str:
    return (st.logs / f"{name}.log").read_text(errors="replace")


def _builds(st: Stack) -> int:
    return _log(st).count(BUILT)


def test_concurrent_reports_build_once_and_leave_other_teams_alone(lab):
    a = lab.client()
    b = lab.client()
    b.headers["Authorization"] = f"Bearer {lab.other_key}"
    jid = submit(a, TINY_SPEC, name="report-load")["id"]
    before = _builds(lab)

    def report(_):
        r = a.get(f"/jobs/{jid}/report", timeout=120)
        return r.status_code, r.headers.get("retry-after"), r.text

    def jobs(_):
        t0 = time.monotonic()
        r = b.get("/jobs", timeout=60)
        return r.status_code, time.monotonic() - t0

    with ThreadPoolExecutor(30) as pool:
        reports = pool.map(report, range(20))
        time.sleep(0.5)  # the team's requests are in: the build is running
        other = list(pool.map(jobs, range(10)))
        reports = list(reports)
    codes = [c for c, _, _ in reports]
    pages = {t for c, _, t in reports if c == 200}
    print(
        f"\n[{lab.kind}] 20 report requests: {codes.count(200)} x 200, {codes.count(429)} x 429; "
        f"builds {_builds(lab) - before}; other team's GET /jobs: "
        f"{[c for c, _ in other]}, slowest {max(s for _, s in other):.2f} s"
    )
    assert set(codes) <= {200, 429}, codes
    assert codes.count(200) >= 1 and len(pages) == 1  # everyone got the one page
    assert all(int(ra) >= 1 for c, ra, _ in reports if c == 429)
    assert _builds(lab) - before == 1
    assert [c for c, _ in other] == [200] * 10
    # the same progress: kept, no build
    assert a.get(f"/jobs/{jid}/report", timeout=60).text in pages
    assert _builds(lab) - before == 1
    # two other jobs build at once; a third of the same team is refused meanwhile (on
    # an API whose builds each take 3 s more: a queued job's report has no records to
    # read or draw, and is built in milliseconds)
    more = [submit(a, {**TINY_SPEC, "seed": s})["id"] for s in (11, 12, 13)]
    port = free_port()
    lab.start("api-slow", [sys.executable, "-c", SLOW_API, str(port)])
    slow = f"http://127.0.0.1:{port}"
    lab.wait_http(slow + "/readyz", "api-slow")
    c = httpx.Client(base_url=slow + API, headers=a.headers, timeout=120)
    with c, ThreadPoolExecutor(3) as pool:
        first = [pool.submit(c.get, f"/jobs/{j}/report") for j in more[:2]]
        lab.wait_log("api-slow", STARTED, count=2)  # both builds are running
        third = c.get(f"/jobs/{more[2]}/report")
        done = [f.result() for f in first]
    assert [r.status_code for r in done] == [200, 200]
    assert third.status_code == 429 and int(third.headers["retry-after"]) >= 1, third.text
    assert "REPORT_BUILDS_PER_TEAM" in third.json()["detail"]
    lab.stop("api-slow")


def _sign_in(base: str, key: str) -> httpx.Client:
    c = httpx.Client(base_url=base, timeout=30)
    page = c.get("/login")
    token = re.search(r'name="csrf_token" value="([^"]+)"', page.text).group(1)
    r = c.post("/login", data={"key": key, "csrf_token": token, "next": "/jobs"})
    assert r.status_code == 303, r.text
    return c


def test_sign_out_at_one_api_process_ends_a_copied_cookie_at_another(lab):
    second = lab.start_api("api-2", env={"SVROBS_SECRET_KEY": "it-secret-0123456789abcdef"})
    try:
        browser = _sign_in(lab.base_url, lab.key)
        copied = httpx.Client(base_url=second, cookies=dict(browser.cookies), timeout=30)
        assert copied.get("/jobs").status_code == 200
        assert copied.get(f"{API}/jobs").status_code == 200
        token = re.search(r'name="csrf_token" value="([^"]+)"', browser.get("/jobs").text)
        assert browser.post("/logout", data={"csrf_token": token.group(1)}).status_code == 303
        r = copied.get("/jobs")
        assert r.status_code == 303 and r.headers["location"].startswith("/login")
        assert copied.get(f"{API}/jobs").status_code == 401
    finally:
        lab.stop("api-2")


def test_300_bad_keys_from_one_address_are_mostly_429(lab):
    base = lab.start_api("api-auth", env={"SVROBS_AUTH_FAILURES_PER_MINUTE": "10"})
    try:
        bad = httpx.Client(
            base_url=base + API, timeout=30, headers={"Authorization": "Bearer svr_bad_" + "x" * 32}
        )
        t0 = time.monotonic()
        codes = [bad.get("/jobs").status_code for _ in range(300)]
        elapsed = time.monotonic() - t0
        refused = bad.get("/jobs")
        good = httpx.Client(
            base_url=base + API, timeout=30, headers={"Authorization": f"Bearer {lab.key}"}
        ).get("/jobs")
        print(
            f"\n[{lab.kind}] 300 bad keys in {elapsed:.1f} s: {codes.count(401)} x 401, "
            f"{codes.count(429)} x 429; Retry-After {refused.headers.get('retry-after')} s; "
            f"a valid key from that address then: {good.status_code}"
        )
        assert set(codes) == {401, 429}
        assert codes[:10] == [401] * 10
        # a token comes back every 6 s: at most that many more 401s
        assert codes.count(401) <= 10 + math.ceil(elapsed / 6) + 1
        assert refused.status_code == 429 and 1 <= int(refused.headers["retry-after"]) <= 6
        assert good.status_code == 429
        time.sleep(int(refused.headers["retry-after"]) + 0.5)
        assert bad.get("/jobs").status_code == 401  # one token back
    finally:
        lab.stop("api-auth")


# an app served as the API is (service.http.request_deadlines): /slow answers in 3 s,
# /late reads its body after 3 s; each answers with the length of the body it read;
# a WebSocket is accepted and kept until the client leaves
SLOW_ROUTE = """
import asyncio, logging, sys, uvicorn
from service.http.request_deadlines import PROTOCOL
logging.basicConfig(level=logging.INFO)
async def app(scope, receive, send):
    if scope["type"] == "websocket":
        await receive()
        await send({"type": "websocket.accept"})
        while (await receive())["type"] != "websocket.disconnect":
            pass
        return
    if scope["type"] != "http":
        return
    if scope["path"] in ("/slow", "/late"):
        await asyncio.sleep(3)
    size, more = 0, True
    while more:
        message = await receive()
        size += len(message.get("body", b""))
        more = message.get("more_body", False)
    body = str(size).encode()
    await send({"type": "http.response.start", "status": 200,
                "headers": [(b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})
uvicorn.run(app, host="127.0.0.1", port=int(sys.argv[1]), http=PROTOCOL, log_level="info")
"""


def _closed_within(sock, seconds: float) -> bytes | None:
    """What the server sent before closing the connection (b"" for nothing), or None
    if it was still open after ``seconds``."""
    import socket

    sock.settimeout(0.5)
    got, deadline = b"", time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            data = sock.recv(65536)
        except socket.timeout:
            continue
        if not data:
            return got
        got += data
    return None


def _response(sock) -> bytes:
    """One whole HTTP response with a Content-Length, however it is split into reads."""
    sock.settimeout(10)
    got = b""
    while b"\r\n\r\n" not in got:
        data = sock.recv(65536)
        assert data, f"closed before a whole response: {got!r}"
        got += data
    head, _, body = got.partition(b"\r\n\r\n")
    length = next(
        int(line.split(b":", 1)[1])
        for line in head.split(b"\r\n")
        if line.lower().startswith(b"content-length:")
    )
    while len(body) < length:
        data = sock.recv(65536)
        assert data, f"closed before a whole response: {got!r}"
        body += data
    return head + b"\r\n\r\n" + body


def _trickled(sock) -> bool:
    """Send a body 10 bytes every 0.2 s (for at most 20 s) -> whether the server
    closed the connection (within 30 s of the last bytes)."""
    try:
        for _ in range(100):
            sock.sendall(b" " * 10)
            if _closed_within(sock, 0.2) is not None:
                return True
    except (BrokenPipeError, ConnectionResetError):
        return True
    return _closed_within(sock, 30) is not None


def test_a_request_whose_headers_never_end_is_closed(lab):
    """A client that sends a request's headers a byte now and then (slowloris) is cut
    off SVROBS_HEADER_TIMEOUT_SECONDS after the connection opened, or after its last
    response on a kept-alive connection; a request that completes its headers in time
    is answered (plain uvicorn keeps such a connection open for good); headers over
    64 KiB are cut off too (httptools reads any size)."""
    import socket

    url = lab.start_api(
        "api-headers",
        env={"SVROBS_HEADER_TIMEOUT_SECONDS": "1", "SVROBS_BODY_TIMEOUT_SECONDS": "1"},
    )
    host, port = url.removeprefix("http://").split(":")
    partial = b"GET /healthz HTTP/1.1\r\nHost: x\r\n"
    with socket.create_connection((host, int(port))) as s:
        s.sendall(partial)
        for _ in range(3):
            time.sleep(0.2)
            s.sendall(b"X-Slow: 1\r\n")  # bytes keep coming, the headers never end
        assert _closed_within(s, 30) == b""
    with socket.create_connection((host, int(port))) as s:
        s.sendall(partial + b"\r\n")  # complete: answered, the connection kept alive
        assert _response(s).startswith(b"HTTP/1.1 200")  # the body is read whole
        s.sendall(partial)  # the next request's headers never end
        assert _closed_within(s, 30) == b""
    body = b'{"name": "' + b"n" * 900_000 + b'"}'  # a body sent with its headers: read
    head = f"POST /api/v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Length: {len(body)}\r\n"
    with socket.create_connection((host, int(port))) as s:
        s.sendall(head.encode() + b"Content-Type: application/json\r\n\r\n" + body)
        s.settimeout(10)
        assert s.recv(65536).startswith(b"HTTP/1.1 401")  # no key: refused, not cut off
    with socket.create_connection((host, int(port))) as s:
        s.sendall(partial + b"X-Big: " + b"b" * 100_000)  # headers of 100 KB: cut off
        assert _closed_within(s, 30) == b""
    big = b"{" + b" " * 5_000_000 + b"}"  # over the body limit: 413 before it is all sent
    head = f"POST /api/v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Length: {len(big)}\r\n\r\n"
    with socket.create_connection((host, int(port))) as s:
        s.sendall(head.encode() + big)  # the rest of the body is read, not cut off
        s.settimeout(10)
        assert s.recv(65536).startswith(b"HTTP/1.1 413")
    head = "POST /api/v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Length: 6000\r\n\r\n"
    with socket.create_connection((host, int(port))) as s:
        s.sendall(head.encode())
        for _ in range(15):  # 2,000 bytes/s for 3 s: 1 s + 1 s per 500 bytes, answered
            time.sleep(0.2)
            s.sendall(b" " * 400)
        assert _response(s).startswith(b"HTTP/1.1 401")  # read whole, then refused
    head = "POST /api/v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Length: 1000\r\n\r\n"
    with socket.create_connection((host, int(port))) as s:
        s.sendall(head.encode())
        assert _trickled(s)  # 10 bytes every 0.2 s: cut off
    log = _log(lab, "api-headers")
    assert "no complete request headers in 1 s" in log
    assert "request body not whole in 1 s plus 1 s per 500 bytes received" in log
    assert log.count("headers over 65536 bytes") == 1, log[-3000:]
    lab.stop("api-headers")


def test_headers_are_bounded_while_a_request_is_answered(lab):
    """While a request is answered (3 s, past the 1 s deadline), it is not cut off,
    nor is a pipelined request behind it, nor a WebSocket opened after a request on
    the same connection; but a pipelined request's headers are counted: past 64 KiB
    the connection closes."""
    import socket

    port = free_port()
    lab.start(
        "api-pipe",
        [sys.executable, "-c", SLOW_ROUTE, str(port)],
        env={"SVROBS_HEADER_TIMEOUT_SECONDS": "1"},
    )
    lab.wait_http(f"http://127.0.0.1:{port}/", "api-pipe")
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(b"GET /slow HTTP/1.1\r\nHost: x\r\n\r\n")
        s.settimeout(10)
        assert s.recv(65536).startswith(b"HTTP/1.1 200")  # after 3 s: answered
    with socket.create_connection(("127.0.0.1", port)) as s:  # two pipelined: both answered
        s.sendall(b"GET /slow HTTP/1.1\r\nHost: x\r\n\r\n" * 2)
        assert _response(s).startswith(b"HTTP/1.1 200")
        assert _response(s).startswith(b"HTTP/1.1 200")  # after 6 s, its own 3 s counted
    upgrade = (
        b"GET /ws HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    with socket.create_connection(("127.0.0.1", port)) as s:  # a WebSocket after a GET
        s.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
        assert _response(s).startswith(b"HTTP/1.1 200")
        s.sendall(upgrade)
        s.settimeout(10)
        assert s.recv(65536).startswith(b"HTTP/1.1 101")
        assert _closed_within(s, 3) is None  # past the 1 s header deadline: still open
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(b"GET /slow HTTP/1.1\r\nHost: x\r\n\r\nGET / HTTP/1.1\r\nX-Big: ")
        try:
            for _ in range(50):  # 1 MB of header while /slow is answered
                s.sendall(b"b" * 20_000)
                time.sleep(0.02)
        except (BrokenPipeError, ConnectionResetError):
            pass  # closed while sending: what is checked
        assert _closed_within(s, 30) is not None
    assert "request headers over 65536 bytes" in _log(lab, "api-pipe")
    lab.stop("api-pipe")


def test_a_body_is_timed_only_while_the_server_reads_it(lab):
    """With a 1.6 s body timeout (and no time earned per byte), against an app that
    reads its body after 3 s: a 1 MB body whose rest is sent 0.3 s after the app
    starts reading is answered whole (uvicorn stopped reading meanwhile, so the
    client could not send: the timeout counts from when it can), and so is a body
    sent 0.3 s after the 100 Continue the app's first read sends; a body that
    trickles is cut off."""
    import socket

    port = free_port()
    lab.start(
        "api-body",
        [sys.executable, "-c", SLOW_ROUTE, str(port)],
        env={"SVROBS_BODY_TIMEOUT_SECONDS": "1.6", "SVROBS_BODY_MIN_BYTES_PER_SECOND": "1e12"},
    )
    lab.wait_http(f"http://127.0.0.1:{port}/", "api-body")

    def post(path: str, size: int) -> bytes:
        return f"POST {path} HTTP/1.1\r\nHost: x\r\nContent-Length: {size}\r\n\r\n".encode()

    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(post("/late", 1_000_000) + b"x" * 300_000)  # reading pauses
        time.sleep(3.3)  # the app reads from 3 s on; the deadline is then 1.6 s away
        s.sendall(b"x" * 700_000)
        assert _response(s).endswith(b"\r\n\r\n1000000")
    with socket.create_connection(("127.0.0.1", port)) as s:  # the body once asked for
        s.sendall(post("/late", 5).replace(b"\r\n\r\n", b"\r\nExpect: 100-continue\r\n\r\n"))
        s.settimeout(10)
        assert s.recv(65536).startswith(b"HTTP/1.1 100 Continue")  # after 3 s
        time.sleep(0.3)
        s.sendall(b"hello")
        assert _response(s).endswith(b"\r\n\r\n5")
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(post("/", 6_000))
        assert _trickled(s)
    assert _log(lab, "api-body").count("request body not whole in 1.6 s") == 1
    lab.stop("api-body")
