"""Running the ``svrobs`` CLI in tests: in process through the console-script entry (so
errors are one line and exit status 2, as for a user), or as a real process; and a
fake API in process (:func:`fake_api`) for answers no svrobs server gives."""

from __future__ import annotations

import os
import subprocess
import sys

import httpx

import svrobs_client.client
from svrobs_cli.app import app
from tests.integration.stack import ROOT


def run_cli(capsys, *args) -> tuple[int, str, str]:
    """``(exit status, stdout, stderr)`` of ``svrobs ARGS`` run in this process."""
    try:
        app([str(a) for a in args])
        code = 0
    except SystemExit as e:
        code = e.code or 0
    out, err = capsys.readouterr()
    return code, out, err


def run_process(stack, *args, timeout: float = 200) -> subprocess.CompletedProcess:
    """``python -m svrobs_cli ARGS`` as a real process against ``stack``'s server."""
    return subprocess.run(
        [sys.executable, "-m", "svrobs_cli", *map(str, args)],
        cwd=ROOT,
        env={**os.environ, "SVROBS_URL": stack.base_url, "SVROBS_API_KEY": stack.key},
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def fake_api(monkeypatch, handler) -> None:
    """Every ``svrobs_client.Client`` made from here on sends its requests to
    ``handler(request) -> httpx.Response`` in this process (no server)."""
    real = httpx.Client
    transport = httpx.MockTransport(handler)
    monkeypatch.setattr(
        svrobs_client.client.httpx, "Client", lambda **kw: real(transport=transport, **kw)
    )
