"""The harness's ports (tests/integration/stack.py): a port taken between the check and
the server's bind must not make a test talk to another process's server, and two test
processes on one machine (the xdist workers, a second suite, `make test-faults`) never
draw from the same block of ports."""

from __future__ import annotations

import subprocess
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import httpx
import pytest

from . import stack as stack_module
from .stack import ROOT, Stack

pytestmark = pytest.mark.integration


class _Impostor(BaseHTTPRequestHandler):
    """Another process's server: 200 on every path."""

    def do_GET(self):  # noqa: N802 - the http.server hook
        body = b'{"impostor": true}'
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


def test_a_port_taken_after_the_check_is_not_mistaken_for_the_api(tmp_path, monkeypatch):
    """The first port the harness draws is taken (after its check) by a server that
    answers 200 at once; the API child cannot bind it. start_api must not hand out that
    server's address: it sees its child fail to bind and starts it on another port."""
    impostor = ThreadingHTTPServer(("127.0.0.1", stack_module.free_port()), _Impostor)
    threading.Thread(target=impostor.serve_forever, daemon=True).start()
    drawn = [impostor.server_address[1]]
    real = stack_module.free_port
    monkeypatch.setattr(stack_module, "free_port", lambda: drawn.pop() if drawn else real())
    st = Stack("embedded", tmp_path)
    try:
        st.setup()
        url = st.start_api()
        assert not url.endswith(f":{impostor.server_address[1]}"), url
        assert "impostor" not in httpx.get(url + "/readyz").text
        with st.client() as c:
            assert c.get("/jobs").status_code == 200  # the stack's own API and key
        assert "address already in use" in (st.logs / "api.1.log").read_text()
    finally:
        st.teardown()
        impostor.shutdown()
        impostor.server_close()


def test_two_test_processes_draw_from_different_port_blocks():
    """This process holds its block; a second process gets another one."""
    mine = stack_module._claim_block()
    other = subprocess.run(
        [
            sys.executable,
            "-c",
            "from tests.integration import stack; print(stack._claim_block(), stack.free_port())",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    base, port = int(other[0]), int(other[1])
    assert base != mine
    assert base <= port < base + stack_module._PORT_BLOCK
    assert not mine <= port < mine + stack_module._PORT_BLOCK
