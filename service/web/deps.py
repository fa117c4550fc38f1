"""FastAPI dependencies of the web pages: the signed-in viewer and the CSRF check.

A viewer is the :class:`~svrobs_lab.auth.Caller` of the session's key, found by the
same rule as the API (:func:`service.http.deps.caller_of`) and rate-limited like it
(a 429 page), so pages see exactly what the key sees over REST.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Form, Header, Request
from sqlalchemy.orm import Session

from service.db.models import ApiKey
from service.http.deps import caller_of, get_db, rate_limit
from service.web.render import SignInRequired, WebError
from svrobs_lab.auth import Caller
from svrobs_lab.sessions import Signer, WebSession, request_session, session_key, signer_of


@dataclass(frozen=True)
class Viewer:
    caller: Caller
    email: str | None
    session: WebSession
    csrf: str

    @property
    def team_id(self) -> int:
        return self.caller.team_id


def web_signer(request: Request) -> Signer:
    """The app's session signer: ``mount_web`` sets it, so every page has one."""
    signer = signer_of(request.app)
    assert signer is not None, "the web UI is mounted by mount_web, which sets the signer"
    return signer


def get_viewer(request: Request, db: Annotated[Session, Depends(get_db)]) -> Viewer:
    """The signed-in viewer, else SignInRequired (a redirect to /login)."""
    found: dict[str, ApiKey | None] = {}

    def find(s: Session) -> ApiKey | None:
        found["key"] = key = session_key(request, s)
        return key

    caller = caller_of(request, db, find)
    if caller is None:
        raise SignInRequired()
    rate_limit(request, caller)  # RateLimited: a 429 page (service.web.errors)
    key = found["key"]
    ws = request_session(request)
    # a caller is found only by the key of a live session (session_key)
    assert key is not None and ws is not None
    return Viewer(
        caller=caller,
        email=key.user.email if key.user is not None else None,
        session=ws,
        csrf=web_signer(request).csrf(ws),
    )


def check_csrf(
    request: Request,
    csrf_token: Annotated[str | None, Form()] = None,
    x_csrf_token: Annotated[str | None, Header()] = None,
) -> None:
    """403 unless the form field or the htmx header carries this session's token."""
    token = csrf_token or x_csrf_token
    if not web_signer(request).csrf_ok(request_session(request), token):
        raise WebError(
            403,
            "The form's security token is missing or out of date. Reload the page and try again.",
        )


CurrentViewer = Annotated[Viewer, Depends(get_viewer)]
CSRF = Depends(check_csrf)
