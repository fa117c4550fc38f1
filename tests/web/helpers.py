"""Signing a TestClient in through the login form (the tests' one way to a session)."""

from __future__ import annotations

import re

CSRF_RE = re.compile(r'name="csrf_token" value="([^"]+)"')


def csrf_of(html: str) -> str:
    return CSRF_RE.search(html).group(1)


def sign_in(client, key: str):
    page = client.get("/login")
    assert page.status_code == 200
    return client.post(
        "/login",
        data={"key": key, "csrf_token": csrf_of(page.text), "next": "/jobs"},
        follow_redirects=False,
    )
