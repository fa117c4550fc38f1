"""Sign-out on the server, failed authentications throttled per address, the security
headers of every HTML response, an Idempotency-Key reused with another name or tags,
and the shortest share link."""

from __future__ import annotations

from contextlib import nullcontext

import pytest

from service.http.security import CSP
from svrobs_lab import reports
from tests.service.svc_helpers import TINY_SPEC
from tests.web.helpers import csrf_of, sign_in

API = "/api/v1"


@pytest.fixture
def web(build_client):
    client, _ = build_client(SECRET_KEY="test-secret-0123456789")
    return client


def test_sign_out_ends_the_session_for_every_copy_of_the_cookie(web, make_account):
    acc = make_account()
    assert sign_in(web, acc.key).status_code == 303
    copied = dict(web.cookies)
    thief = type(web)(web.app, cookies=copied)
    assert thief.get("/jobs", follow_redirects=False).status_code == 200
    assert thief.get(f"{API}/jobs").status_code == 200  # the cookie reads the API
    token = csrf_of(web.get("/jobs").text)
    assert (
        web.post("/logout", data={"csrf_token": token}, follow_redirects=False).status_code == 303
    )
    r = thief.get("/jobs", follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"].startswith("/login")
    assert thief.get(f"{API}/jobs").status_code == 401
    # signing in again is a new session; the old cookie stays out
    assert sign_in(web, acc.key).status_code == 303
    assert web.get("/jobs", follow_redirects=False).status_code == 200
    assert thief.get("/jobs", follow_redirects=False).status_code == 303


def test_bad_bearer_keys_are_throttled_per_address(build_client, make_account):
    client, _ = build_client(AUTH_FAILURES_PER_MINUTE=10)
    acc = make_account()
    bad = {"Authorization": "Bearer svr_nothing_" + "x" * 30}
    codes = [client.get(f"{API}/jobs", headers=bad).status_code for _ in range(30)]
    assert codes[:10] == [401] * 10 and set(codes[10:]) == {429}
    r = client.get(f"{API}/jobs", headers=bad)
    assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1
    assert r.json()["detail"].startswith("too many failed authentications")
    # the address is refused before its key is looked up: a right key waits too
    assert client.get(f"{API}/jobs", headers=acc.headers).status_code == 429
    # another address is not
    other = type(client)(client.app, client=("10.0.0.2", 5000))
    assert other.get(f"{API}/jobs", headers=acc.headers).status_code == 200
    assert other.get(f"{API}/jobs", headers=bad).status_code == 401


@pytest.mark.parametrize(
    "a, b, same",
    [
        ("2001:db8:1:2::1", "2001:db8:1:2:ffff:ffff:ffff:ffff", True),  # one /64
        ("2001:db8:1:2::1", "2001:db8:1:3::1", False),
        ("::ffff:192.0.2.7", "192.0.2.7", True),  # IPv4-mapped is the IPv4 address
        ("192.0.2.7", "192.0.2.8", False),
        ("unknown", "unknown", True),
    ],
)
def test_failed_authentications_count_per_ipv4_address_and_ipv6_64(a, b, same):
    """A bucket per IPv4 address and per IPv6 /64: the addresses of one /64 share
    theirs, so a host given a /64 cannot spread its guesses over 2^64 buckets."""
    from service.http.auth_throttle import AuthThrottle, throttled_as
    from svrobs_lab.errors import RateLimited

    throttle = AuthThrottle(per_minute=2)
    for _ in range(2):
        throttle.failed(throttled_as(a))
    with pytest.raises(RateLimited, match="too many failed") if same else nullcontext():
        throttle.check(throttled_as(b))
    assert (throttled_as(a) == throttled_as(b)) is same


def test_bad_sign_ins_are_throttled_with_a_429_page(build_client, make_account):
    client, _ = build_client(SECRET_KEY="s" * 24, AUTH_FAILURES_PER_MINUTE=3)
    acc = make_account()
    codes = [sign_in(client, acc.key + "x").status_code for _ in range(5)]
    assert codes == [401, 401, 401, 429, 429]
    r = sign_in(client, acc.key)
    assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1
    assert "text/html" in r.headers["content-type"] and "failed authentications" in r.text


def test_throttle_off_with_zero(build_client):
    client, _ = build_client(AUTH_FAILURES_PER_MINUTE=0)
    bad = {"Authorization": "Bearer nope"}
    assert {client.get(f"{API}/jobs", headers=bad).status_code for _ in range(15)} == {401}


def _security_headers(r, csp_has=("frame-ancestors 'none'", "script-src 'self'")):
    assert r.headers["x-content-type-options"] == "nosniff", r.url
    assert r.headers["referrer-policy"] == "same-origin", r.url
    csp = r.headers["content-security-policy"]
    for part in csp_has:
        assert part in csp, (r.url, csp)
    assert "'unsafe-inline'" not in csp.split("script-src", 1)[1].split(";")[0]


def test_every_html_response_has_the_security_headers(web, make_account, monkeypatch):
    page = "<html><head><style>p{}</style></head><body><p>report</p></body></html>"
    monkeypatch.setattr(reports, "job_report_html", lambda *a, **k: page)
    acc = make_account()
    jid = web.post(f"{API}/jobs", json=TINY_SPEC, headers=acc.headers).json()["id"]
    api_report = web.get(f"{API}/jobs/{jid}/report", headers=acc.headers)
    assert api_report.status_code == 200 and api_report.headers["content-type"].startswith(
        "text/html"
    )
    _security_headers(api_report)
    link = web.post(f"{API}/jobs/{jid}/shares", json={"days": 1}, headers=acc.headers)
    token = link.json()["url"].rsplit("/", 1)[1]
    shared = web.get(f"/s/{token}/report")
    assert shared.status_code == 200
    _security_headers(shared)
    for path in ("/login", "/docs", "/redoc", "/s/nosuchtoken"):
        r = web.get(path)
        assert r.headers["content-type"].startswith("text/html"), path
        _security_headers(r)
    assert web.get("/login").headers["content-security-policy"] == CSP  # the dashboard's
    sign_in(web, acc.key)
    _security_headers(web.get(f"/jobs/{jid}/report"))
    # JSON is not sniffed either
    assert (
        web.get(f"{API}/jobs", headers=acc.headers).headers["x-content-type-options"] == "nosniff"
    )


def test_idempotency_key_reused_with_another_name_or_tags_is_409(client, make_account):
    acc = make_account()
    h = {**acc.headers, "Idempotency-Key": "k-1"}
    body = {**TINY_SPEC, "name": "a", "tags": ["x", "y"]}
    first = client.post(f"{API}/jobs", json=body, headers=h)
    assert first.status_code == 202, first.text
    again = client.post(f"{API}/jobs", json={**body, "tags": ["y", "x"]}, headers=h)
    assert again.json()["id"] == first.json()["id"]  # the same request (tags as a set)
    for change, what in (
        ({"name": "b"}, "name"),
        ({"tags": ["x"]}, "tags"),
        ({"seed": 99}, "spec"),
    ):
        r = client.post(f"{API}/jobs", json={**body, **change}, headers=h)
        assert r.status_code == 409, r.text
        assert r.json()["field"] == "Idempotency-Key" and f"different {what}" in r.json()["detail"]
    assert client.get(f"{API}/jobs", headers=acc.headers).json()["total"] == 1


@pytest.mark.parametrize("days", [1e-300, 0.04, 0, -1])
def test_a_share_link_lasts_at_least_an_hour(client, make_account, days):
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=TINY_SPEC, headers=acc.headers).json()["id"]
    r = client.post(f"{API}/jobs/{jid}/shares", json={"days": days}, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "days", r.text
    ok = client.post(f"{API}/jobs/{jid}/shares", json={"days": 1 / 24}, headers=acc.headers)
    assert ok.status_code == 201, ok.text


def test_the_share_form_refuses_less_than_an_hour(web, make_account):
    acc = make_account()
    jid = web.post(f"{API}/jobs", json=TINY_SPEC, headers=acc.headers).json()["id"]
    sign_in(web, acc.key)
    page = web.get(f"/jobs/{jid}/share")
    assert 'min="0.0417"' in page.text  # the browser's own check: not under an hour
    token = csrf_of(page.text)
    r = web.post(f"/jobs/{jid}/share", data={"csrf_token": token, "days": "1e-300"})
    assert r.status_code == 422 and "days" in r.text
    ok = web.post(
        f"/jobs/{jid}/share", data={"csrf_token": token, "days": "0.0417"}, follow_redirects=False
    )
    assert ok.status_code == 303
