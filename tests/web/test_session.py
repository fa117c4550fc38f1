"""The session cookie and CSRF rules (svrobs_lab.sessions) through the app: a signed
cookie is a session until it is tampered with, expires or its key is revoked; a
state-changing form without this session's token is a 403; the key never shows."""

from __future__ import annotations

import errno
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import timedelta

import pytest
from fastapi.testclient import TestClient

from service.db import accounts
from service.db.models import utcnow
from service.web.render import safe_next
from svrobs_lab import sessions
from svrobs_lab.sessions import COOKIE, Signer, load_secret
from tests.service.svc_helpers import make_settings

from .helpers import csrf_of, sign_in


@pytest.fixture
def web(build_client):
    client, _ = build_client(SECRET_KEY="test-secret-0123456789", SESSION_HOURS=1.0)
    return client


def test_sign_in_sets_a_signed_httponly_strict_cookie_without_the_key(web, make_account):
    acc = make_account()
    r = sign_in(web, acc.key)
    assert r.status_code == 303 and r.headers["location"] == "/jobs"
    header = r.headers["set-cookie"]
    assert header.startswith(f"{COOKIE}=")
    low = header.lower()
    assert "httponly" in low and "samesite=strict" in low and "max-age=3600" in low
    assert "secure" not in low  # plain http: a Secure cookie would never come back
    assert acc.key not in header and acc.key.split("_", 2)[2] not in header
    page = web.get("/jobs")
    assert page.status_code == 200 and acc.user.email in page.text
    assert acc.key not in page.text


def test_wrong_key_stays_signed_out_and_is_not_echoed(web, make_account):
    acc = make_account()
    wrong = acc.key[:-3] + "xyz"
    r = sign_in(web, wrong)
    assert r.status_code == 401 and "Invalid, revoked or expired" in r.text
    assert wrong not in r.text
    assert web.get("/jobs", follow_redirects=False).status_code == 303


@pytest.mark.parametrize("hours, shown", [(12.0, "12 hours"), (1.0, "1 hour."), (0.5, "0.5 hours")])
def test_the_sign_in_page_says_where_a_key_comes_from_and_how_long_a_session_lasts(
    build_client, hours, shown
):
    client, _ = build_client(SECRET_KEY="test-secret-0123456789", SESSION_HOURS=hours)
    text = " ".join(client.get("/login").text.split())
    assert "the admin key <code>make run</code> printed on its first start" in text
    assert "<code>svrobs admin create-key EMAIL</code>" in text
    assert f"a signed session cookie for {shown}" in text


def test_pages_redirect_to_login_without_a_session(web):
    r = web.get("/jobs?status=running", follow_redirects=False)
    assert r.status_code == 303
    assert r.headers["location"] == "/login?next=%2Fjobs%3Fstatus%3Drunning"
    assert web.get("/", follow_redirects=False).headers["location"] == "/login"
    r = web.get("/jobs/rows", headers={"HX-Request": "true"}, follow_redirects=False)
    assert r.status_code == 401 and r.headers["hx-redirect"].startswith("/login")


def test_tampered_cookie_is_signed_out(web, make_account):
    acc = make_account()
    sign_in(web, acc.key)
    value = web.cookies[COOKIE]
    payload, mac = value.split(".")
    flipped = payload[:-1] + ("A" if payload[-1] != "A" else "B")
    for bad in (f"{flipped}.{mac}", f"{payload}.{mac[:-1]}x", payload, "garbage"):
        web.cookies.set(COOKIE, bad)
        assert web.get("/jobs", follow_redirects=False).status_code == 303, bad


def test_another_secret_or_an_expired_session_is_signed_out():
    signer = Signer(b"one", session_hours=1)
    s = signer.new(key_id=5, now=1000.0)
    cookie = signer.dumps(s)
    assert signer.loads(cookie, now=1000.0 + 3599) == s
    assert signer.loads(cookie, now=1000.0 + 3600) is None  # expired
    assert Signer(b"two", session_hours=1).loads(cookie, now=1000.0) is None
    # the expiry is inside the signed payload: it cannot be extended
    forged = Signer(b"one", session_hours=100).new(key_id=5, now=1000.0)
    assert signer.loads(Signer(b"two", session_hours=100).dumps(forged), now=5000.0) is None


def test_expired_cookie_through_the_app(build_client, make_account, session):
    client, _ = build_client(SECRET_KEY="k" * 20, SESSION_HOURS=1.0)
    acc = make_account()
    signer = Signer(b"k" * 20, session_hours=1.0)
    old = signer.new(key_id=acc.key_row.id, now=time.time() - 3601)
    client.cookies.set(COOKIE, signer.dumps(old))
    assert client.get("/jobs", follow_redirects=False).status_code == 303
    fresh = signer.new(key_id=acc.key_row.id)
    client.cookies.set(COOKIE, signer.dumps(fresh))  # signed, but never signed in
    assert client.get("/jobs", follow_redirects=False).status_code == 303
    kept = sessions.sign_in(session, signer, acc.key_row.id)
    client.cookies.set(COOKIE, signer.dumps(kept))
    assert client.get("/jobs", follow_redirects=False).status_code == 200


@pytest.mark.parametrize("how", ["revoke", "expire"])
def test_revoking_or_expiring_the_key_ends_its_sessions(web, make_account, session, how):
    acc = make_account()
    sign_in(web, acc.key)
    assert web.get("/jobs", follow_redirects=False).status_code == 200
    assert web.get(f"/api/v1/jobs/{999}").status_code == 404  # the cookie reads the API
    if how == "revoke":
        accounts.revoke_key(session, acc.key_row.prefix)
    else:
        acc.key_row.expires_at = utcnow() - timedelta(seconds=1)
    session.commit()
    assert web.get("/jobs", follow_redirects=False).status_code == 303
    assert web.get("/api/v1/jobs").status_code == 401


def test_cookie_authorises_an_api_write_only_with_the_sessions_csrf_token(web, make_account):
    acc = make_account()
    assert web.get("/session").json() == {"signed_in": False}
    sign_in(web, acc.key)
    spec = {"systems": ["paper-stable"], "sigma_w": [1], "N": [10]}
    assert web.post("/api/v1/jobs", json=spec).status_code == 401  # the cookie alone
    forged = web.post("/api/v1/jobs", json=spec, headers={"X-CSRF-Token": "x" * 43})
    assert forged.status_code == 401
    other = TestClient(web.app)  # another browser's session and token
    sign_in(other, make_account().key)
    theirs = other.get("/session").json()["csrf"]
    assert web.post("/api/v1/jobs", json=spec, headers={"X-CSRF-Token": theirs}).status_code == 401
    mine = web.get("/session").json()
    assert mine["signed_in"] and mine["email"] == acc.user.email
    assert mine["csrf"] == csrf_of(web.get("/jobs").text)  # the pages' token
    r = web.post("/api/v1/jobs", json=spec, headers={"X-CSRF-Token": mine["csrf"]})
    assert r.status_code == 202 and r.json()["owner"] == acc.user.email
    web.post("/logout", data={"csrf_token": mine["csrf"]})
    assert (
        web.post("/api/v1/jobs", json=spec, headers={"X-CSRF-Token": mine["csrf"]}).status_code
        == 401
    )


def test_state_changing_posts_need_this_sessions_csrf_token(web, make_account):
    acc = make_account()
    sign_in(web, acc.key)
    assert web.post("/logout", data={}, follow_redirects=False).status_code == 403
    r = web.post("/logout", data={"csrf_token": "x" * 43}, follow_redirects=False)
    assert r.status_code == 403 and "security token" in r.text
    token = csrf_of(web.get("/jobs").text)
    r = web.post("/logout", headers={"X-CSRF-Token": token}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/login"
    assert web.get("/jobs", follow_redirects=False).status_code == 303


def test_sign_in_itself_needs_the_login_forms_token(web, make_account):
    acc = make_account()
    r = web.post("/login", data={"key": acc.key}, follow_redirects=False)
    assert r.status_code == 403
    assert web.get("/jobs", follow_redirects=False).status_code == 303


def test_a_new_sign_in_gets_a_new_csrf_token(web, make_account):
    acc = make_account()
    before = csrf_of(web.get("/login").text)
    sign_in(web, acc.key)
    after = csrf_of(web.get("/jobs").text)
    assert before != after
    r = web.post("/logout", data={"csrf_token": before}, follow_redirects=False)
    assert r.status_code == 403


def test_generated_secret_is_kept_across_restarts(tmp_path):
    settings = make_settings("sqlite://", VAR_DIR=str(tmp_path / "var"))
    first = load_secret(settings)
    assert len(first) >= 32 and load_secret(settings) == first
    assert (tmp_path / "var" / "secret_key").stat().st_mode & 0o077 == 0
    assert load_secret(make_settings("sqlite://", SECRET_KEY="abc")) == b"abc"


def test_a_process_killed_while_writing_the_secret_leaves_no_empty_file(tmp_path, monkeypatch):
    """The secret appears under its name only whole: a writer that dies mid-write
    leaves nothing there, and the next start makes one."""
    settings = make_settings("sqlite://", VAR_DIR=str(tmp_path / "var"))

    def killed(*args, **kwargs):
        raise KeyboardInterrupt  # the process ends between creating and writing

    with monkeypatch.context() as m:
        m.setattr(sessions.secrets, "token_urlsafe", killed)
        with pytest.raises(KeyboardInterrupt):
            load_secret(settings)
    assert not (tmp_path / "var" / "secret_key").exists()
    assert len(load_secret(settings)) >= 32
    assert sorted(p.name for p in (tmp_path / "var").iterdir()) == ["secret_key"]


def test_a_state_folder_without_hard_links_still_gets_its_secret(tmp_path, monkeypatch):
    """vfat and some bind mounts refuse os.link (EPERM): the secret is created
    exclusively instead, and kept across starts."""

    def no_links(src, dst, **kwargs):
        raise PermissionError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(sessions.os, "link", no_links)
    settings = make_settings("sqlite://", VAR_DIR=str(tmp_path / "var"))
    first = load_secret(settings)
    assert len(first) >= 32 and load_secret(settings) == first
    assert sorted(p.name for p in (tmp_path / "var").iterdir()) == ["secret_key"]
    assert (tmp_path / "var" / "secret_key").stat().st_mode & 0o077 == 0


def test_concurrent_first_starts_agree_on_one_secret(tmp_path):
    settings = make_settings("sqlite://", VAR_DIR=str(tmp_path / "var"))
    with ThreadPoolExecutor(8) as pool:
        secrets_seen = set(pool.map(lambda _: load_secret(settings), range(32)))
    assert len(secrets_seen) == 1
    assert sorted(p.name for p in (tmp_path / "var").iterdir()) == ["secret_key"]


def test_cookie_is_secure_over_https(build_client, make_account):
    client, _ = build_client(SECRET_KEY="s" * 20)
    client.base_url = "https://testserver"
    acc = make_account()
    r = sign_in(client, acc.key)
    assert r.status_code == 303 and "; secure" in r.headers["set-cookie"].lower()


@pytest.mark.parametrize(("setting", "scheme"), [(True, "http"), (False, "https")])
def test_the_cookie_setting_decides_whatever_the_scheme(
    build_client, make_account, setting, scheme
):
    """Behind a TLS proxy that uvicorn does not trust, every request looks like plain
    http: SVROBS_SESSION_COOKIE_SECURE=true still makes every session cookie Secure (the
    sign-in form's, the signed-in one and its removal), and false never does. The
    browser's cookie is sent as a header (a client keeps no Secure cookie for http)."""
    client, _ = build_client(SECRET_KEY="s" * 20, SESSION_COOKIE_SECURE=setting)
    client.base_url = f"{scheme}://testserver"
    acc = make_account()

    def secure(response) -> bool:
        client.cookies.clear()
        return "; secure" in response.headers["set-cookie"].lower()

    def cookie(response) -> dict:
        return {"Cookie": response.headers["set-cookie"].split(";", 1)[0]}

    form = client.get("/login")
    assert secure(form) is setting
    data = {"key": acc.key, "csrf_token": csrf_of(form.text)}
    r = client.post("/login", data=data, headers=cookie(form), follow_redirects=False)
    assert r.status_code == 303 and secure(r) is setting
    token = csrf_of(client.get("/jobs", headers=cookie(r)).text)
    out = client.post(
        "/logout", data={"csrf_token": token}, headers=cookie(r), follow_redirects=False
    )
    assert out.status_code == 303 and secure(out) is setting


@pytest.mark.parametrize(
    ("target", "followed"),
    [
        ("/jobs/3?x=1", "/jobs/3?x=1"),
        ("https://evil.example/", "/jobs"),
        ("//evil.example/", "/jobs"),
        ("/\t/evil.example/", "/jobs"),
        ("/\\evil.example", "/jobs"),
        ("jobs", "/jobs"),
        ("", "/jobs"),
    ],
)
def test_sign_in_only_returns_to_a_page_of_this_server(target, followed):
    assert safe_next(target) == followed


def test_signed_out_htmx_poll_comes_back_to_its_page(web):
    r = web.get(
        "/jobs/rows?page=2",
        headers={"HX-Request": "true", "HX-Current-URL": "http://testserver/jobs?tag=a"},
        follow_redirects=False,
    )
    assert r.status_code == 401 and r.headers["hx-redirect"] == "/login?next=%2Fjobs%3Ftag%3Da"
