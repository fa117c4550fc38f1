"""Playwright driving Debian's chromium (never a downloaded browser) for the web tests.

:class:`Browser` opens one chromium per test module; every context it makes records
the URL of each request the page sends, so a test can check that nothing went to
another host.
"""

from __future__ import annotations

import os
from pathlib import Path
from urllib.parse import urlsplit

import pytest

CHROMIUM = Path("/usr/bin/chromium")
ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
]

# Milliseconds of latency on every request the pages send (0: none). A hunt for tests
# that act on a page before its deferred scripts have arrived and run:
# SVROBS_TEST_LATENCY_MS=400 pytest tests/web
LATENCY_MS = int(os.environ.get("SVROBS_TEST_LATENCY_MS", "0"))

needs_chromium = pytest.mark.skipif(
    not CHROMIUM.exists(), reason=f"{CHROMIUM} missing (Debian package 'chromium')"
)


class Browser:
    def __init__(self):
        from playwright.sync_api import sync_playwright

        self._pw = sync_playwright().start()
        self.chromium = self._pw.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        self.requests: list[str] = []
        self.console_errors: list[str] = []
        self.servers: set[str] = set()  # host:port of every base_url a page was opened on

    def page(
        self,
        base_url: str,
        *,
        width: int = 1280,
        height: int = 900,
        dark: bool = False,
        js: bool = True,
    ):
        """A fresh context (no cookies) and page on ``base_url``, its requests logged;
        ``dark``: the system asks for a dark colour scheme; ``js=False``: JavaScript off."""
        self.servers.add(urlsplit(base_url).netloc)
        context = self.chromium.new_context(
            base_url=base_url,
            viewport={"width": width, "height": height},
            color_scheme="dark" if dark else "light",
            java_script_enabled=js,
        )
        context.on("request", lambda r: self.requests.append(r.url))
        page = context.new_page()
        if LATENCY_MS:
            conditions = {"latency": LATENCY_MS, "downloadThroughput": -1, "uploadThroughput": -1}
            cdp = context.new_cdp_session(page)
            cdp.send("Network.emulateNetworkConditions", {"offline": False, **conditions})
        page.on(
            "console",
            lambda m: self.console_errors.append(m.text) if m.type == "error" else None,
        )
        page.set_default_timeout(30_000)
        return page

    def foreign_requests(self) -> list[str]:
        """Requests to any host but the servers pages were opened on (data: URLs never
        leave the page, and a blob: URL of a server is the page's own memory, e.g.
        ReDoc's web worker)."""
        inline = ("data:", *(f"blob:http://{s}/" for s in self.servers))
        return [
            u
            for u in self.requests
            if not u.startswith(inline) and urlsplit(u).netloc not in self.servers
        ]

    def close(self) -> None:
        self.chromium.close()
        self._pw.stop()
