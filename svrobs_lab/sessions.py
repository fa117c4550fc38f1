"""The web UI's signed session cookie and its CSRF token.

The cookie holds ``{"s": nonce, "e": expiry}`` and, once signed in, ``"k"``: the id
of the API key used to sign in, never the key itself. It is signed with HMAC-SHA256
under the settings' secret key; a tampered, expired or unsigned cookie is no session.
A signed-in cookie is a session only while the server keeps its sign-in
(:mod:`service.db.sign_ins`, by the nonce's hash): signing out deletes it, so a
copied cookie stops working at once. Every request re-reads the key row, so
revoking or expiring the key ends its sessions at once. The CSRF token is an HMAC of the session's nonce: it changes at
every sign-in and cannot be derived without the secret.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import logging
import os
import secrets
import tempfile
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from sqlalchemy.orm import Session

from service.config import Settings
from service.db import sign_ins
from service.db.accounts import active_key
from service.db.models import ApiKey

log = logging.getLogger(__name__)

COOKIE = "svrobs_session"
SECRET_FILE = "secret_key"
CSRF_FIELD = "csrf_token"  # the hidden form field
CSRF_HEADER = "x-csrf-token"  # htmx requests (hx-headers on <body>)


def secret_folder(settings: Settings) -> Path:
    """Where a generated secret is kept: the state folder (SVROBS_VAR_DIR)."""
    return Path(settings.VAR_DIR)


def load_secret(settings: Settings) -> bytes:
    """SVROBS_SECRET_KEY, else the secret kept in the state folder, made on first use.
    It is written whole to a private temporary file, then linked to its name, which
    fails if another process linked first: the file never exists half written, and
    concurrent API processes agree on one secret."""
    if settings.SECRET_KEY:
        return settings.SECRET_KEY.encode("utf-8")
    path = secret_folder(settings) / SECRET_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists():
        _make_secret(path)
    text = path.read_text().strip()
    if not text:
        raise RuntimeError(f"{path} is empty: delete it or set SVROBS_SECRET_KEY")
    return text.encode("utf-8")


def _make_secret(path: Path) -> None:
    """Write a new secret to ``path`` unless another process has: whole, by a link
    from a private temporary file; where the folder's file system has no hard links,
    by an exclusive create (a writer killed mid-write then leaves it empty, which
    load_secret reports)."""
    secret = secrets.token_urlsafe(48)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{SECRET_FILE}.")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(secret)
            f.flush()
            os.fsync(f.fileno())
        os.link(tmp, path)
    except FileExistsError:
        return
    except OSError:  # no hard links here (EPERM, ENOTSUP, EXDEV ...)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            return
        with os.fdopen(fd, "w") as f:
            f.write(secret)
    finally:
        os.unlink(tmp)
    log.info("generated the web session secret in %s", path)


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode("ascii")


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


@dataclass(frozen=True)
class WebSession:
    nonce: str
    expires: int  # unix seconds
    key_id: int | None = None

    @property
    def signed_in(self) -> bool:
        return self.key_id is not None


class Signer:
    """Signs and verifies session cookies and derives CSRF tokens from one secret."""

    def __init__(self, secret: bytes, *, session_hours: float):
        self._secret = secret
        self.max_age = int(session_hours * 3600)

    def _mac(self, purpose: str, text: str) -> str:
        return _b64(hmac.new(self._secret, f"{purpose}|{text}".encode(), hashlib.sha256).digest())

    def new(self, key_id: int | None = None, now: float | None = None) -> WebSession:
        now = time.time() if now is None else now
        return WebSession(secrets.token_urlsafe(18), int(now) + self.max_age, key_id)

    def dumps(self, s: WebSession) -> str:
        body = {"s": s.nonce, "e": s.expires}
        if s.key_id is not None:
            body["k"] = s.key_id
        payload = _b64(json.dumps(body, separators=(",", ":")).encode())
        return f"{payload}.{self._mac('session', payload)}"

    def loads(self, cookie: str | None, now: float | None = None) -> WebSession | None:
        """The session of a cookie; None if it is missing, tampered or expired."""
        payload, _, mac = (cookie or "").partition(".")
        if not payload or not hmac.compare_digest(mac, self._mac("session", payload)):
            return None
        try:
            body = json.loads(_unb64(payload))
            s = WebSession(str(body["s"]), int(body["e"]), body.get("k"))
        except (ValueError, KeyError, TypeError):
            return None
        if s.key_id is not None and not isinstance(s.key_id, int):
            return None
        if s.expires <= (time.time() if now is None else now):
            return None
        return s

    def csrf(self, s: WebSession) -> str:
        return self._mac("csrf", s.nonce)

    def csrf_ok(self, s: WebSession | None, token: str | None) -> bool:
        if s is None or not token:
            return False
        return hmac.compare_digest(token, self.csrf(s))


def signer_of(app) -> Signer | None:
    """The app's signer (set by ``service.app.create_app``), or None without one."""
    return getattr(app.state, "web_signer", None)


def request_session(request) -> WebSession | None:
    """The verified session of a request's cookie, or None."""
    signer = signer_of(request.app)
    return signer.loads(request.cookies.get(COOKIE)) if signer is not None else None


def session_key(request, session: Session) -> ApiKey | None:
    """The active API key a request's session cookie was signed in with, or None (also
    when the sign-in was ended: :func:`sign_out`)."""
    s = request_session(request)
    if s is None or s.key_id is None or not sign_ins.is_live(session, s.nonce, s.key_id):
        return None
    return active_key(session, s.key_id)


def sign_in(session: Session, signer: Signer, key_id: int) -> WebSession:
    """A new signed-in session of ``key_id``, kept on the server (committed)."""
    s = signer.new(key_id)
    sign_ins.start(session, s.nonce, key_id, datetime.fromtimestamp(s.expires, UTC))
    session.commit()
    return s


def sign_out(session: Session, request) -> None:
    """End the request's signed-in session on the server (committed): its cookie, or
    any copy of it, is no session from now on."""
    s = request_session(request)
    if s is not None and s.signed_in:
        sign_ins.end(session, s.nonce)
        session.commit()


def secure_cookie(request) -> bool:
    """Whether the session cookie is Secure: SVROBS_SESSION_COOKIE_SECURE, else whether
    the request came over https."""
    forced = request.app.state.settings.SESSION_COOKIE_SECURE
    return request.url.scheme == "https" if forced is None else bool(forced)


def set_cookie(response, request, s: WebSession, signer: Signer) -> None:
    response.set_cookie(
        COOKIE,
        signer.dumps(s),
        max_age=max(0, s.expires - int(time.time())),
        httponly=True,
        samesite="strict",
        secure=secure_cookie(request),
        path="/",
    )


def clear_cookie(response, request) -> None:
    response.delete_cookie(
        COOKIE, path="/", httponly=True, samesite="strict", secure=secure_cookie(request)
    )
