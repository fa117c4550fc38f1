"""FastAPI dependencies of the web pages: the signed-in viewer and the CSRF check.

A viewer is the API's :class:`~service.api.deps.Caller` of the session's key, found
by the same rule as the API (``caller_of``) and rate-limited like it, so pages see
exactly what the key sees over REST.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Form, Header, HTTPException, Request
from sqlalchemy.orm import Session

from service.api.deps import Caller, caller_of, get_db, rate_limit
from service.web.render import SignInRequired, WebError
from service.web.session import WebSession, request_session, session_key, signer_of


@dataclass(frozen=True)
class Viewer:
    caller: Caller
    email: str | None
    session: WebSession
    csrf: str

    @property
    def team_id(self) -> int:
        return self.caller.team_id


def get_viewer(request: Request, db: Annotated[Session, Depends(get_db)]) -> Viewer:
    """The signed-in viewer, else SignInRequired (a redirect to /login)."""
    found = {}

    def find(s: Session):
        found["key"] = key = session_key(request, s)
        return key

    caller = caller_of(request, db, find)
    if caller is None:
        raise SignInRequired()
    try:
        rate_limit(request, caller)
    except HTTPException as exc:
        raise WebError(429, str(exc.detail)) from None
    key = found["key"]
    ws = request_session(request)
    return Viewer(
        caller=caller,
        email=key.user.email if key.user is not None else None,
        session=ws,
        csrf=signer_of(request.app).csrf(ws),
    )


def check_csrf(
    request: Request,
    csrf_token: Annotated[str | None, Form()] = None,
    x_csrf_token: Annotated[str | None, Header()] = None,
) -> None:
    """403 unless the form field or the htmx header carries this session's token."""
    token = csrf_token or x_csrf_token
    if not signer_of(request.app).csrf_ok(request_session(request), token):
        raise WebError(
            403,
            "The form's security token is missing or out of date. Reload the page and try again.",
        )


CurrentViewer = Annotated[Viewer, Depends(get_viewer)]
CSRF = Depends(check_csrf)
