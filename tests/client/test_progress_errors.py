"""Which progress bar the client draws where, and errors from bodies that are not the
API's JSON (a proxy's HTML page, a Retry-After header). No server needed."""

from __future__ import annotations

import io
import sys
import types

import pytest

from svrobs_client import errors, progress


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
    assert err.message == "<html><body><h1>502 Bad Gateway</h1> </body></html>"
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
