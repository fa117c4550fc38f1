"""API keys: hashed storage, prefix lookup, revocation, expiry; admin functions."""

from __future__ import annotations

from datetime import timedelta

import pytest

from service.db import accounts
from service.db.accounts import authenticate, hash_key, split_key
from service.db.errors import AdminError
from service.db.models import utcnow

API = "/api/v1"


def test_key_format_and_hash(session, make_account):
    acc = make_account()
    prefix = split_key(acc.key)
    assert acc.key.startswith(f"svr_{prefix}_") and len(prefix) == 8
    assert acc.key_row.prefix == prefix and acc.key_row.key_hash == hash_key(acc.key)
    assert authenticate(session, acc.key).id == acc.key_row.id
    assert authenticate(session, acc.key[:-1] + ("A" if acc.key[-1] != "A" else "B")) is None
    assert authenticate(session, "svr_zzzzzzzz_whatever") is None
    assert authenticate(session, "") is None


def test_revoked_key_401(client, session, make_account):
    acc = make_account()
    assert client.get(f"{API}/jobs", headers=acc.headers).status_code == 200
    accounts.revoke_key(session, acc.key_row.prefix)
    session.commit()
    r = client.get(f"{API}/jobs", headers=acc.headers)
    assert r.status_code == 401 and r.headers["WWW-Authenticate"] == "Bearer"
    assert r.json()["detail"]


def test_expired_key_401(client, session, make_account):
    acc = make_account(expires_at=utcnow() - timedelta(seconds=1))
    assert client.get(f"{API}/jobs", headers=acc.headers).status_code == 401
    fresh = make_account(expires_in_days=1)
    assert client.get(f"{API}/jobs", headers=fresh.headers).status_code == 200


def test_admin_errors(session):
    t = accounts.create_team(session, "lab")
    with pytest.raises(AdminError):
        accounts.create_team(session, "lab")
    accounts.create_user(session, "lab", "A@Lab.org")
    with pytest.raises(AdminError):
        accounts.create_user(session, t.id, "a@lab.org")
    with pytest.raises(AdminError):
        accounts.create_user(session, "nolab", "b@lab.org")
    row, key = accounts.create_key(session, "a@lab.org", name="ci")
    assert row.team_id == t.id and key not in (row.key_hash, row.prefix)
    accounts.revoke_key(session, key)  # by full key too
    assert row.revoked_at is not None
    with pytest.raises(AdminError):
        accounts.revoke_key(session, "nope")


@pytest.mark.parametrize("secret_head", ["_", "__", "-", "_-"])
def test_key_whose_secret_starts_with_a_separator(session, make_account, monkeypatch, secret_head):
    """``token_urlsafe`` starts a secret with ``_`` about once in 64 keys: such a key
    is drawn on purpose here, and it works like any other."""
    real = accounts.secrets.token_urlsafe
    monkeypatch.setattr(accounts.secrets, "token_urlsafe", lambda n: secret_head + real(n)[1:])
    acc = make_account()
    prefix, secret = acc.key.split("_", 2)[1:]
    assert secret.startswith(secret_head) and split_key(acc.key) == prefix
    assert authenticate(session, acc.key).id == acc.key_row.id
    assert authenticate(session, acc.key[: -len(secret)] + secret[1:]) is None
