"""``/``, ``/login`` and ``/logout``: signing in with an API key (checked by the same
rule as the API, :func:`svrobs_lab.auth.bearer_key`) into a signed session cookie;
``/session``: who is signed in and the session's CSRF token (for the API docs page)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Form, Request
from fastapi.responses import JSONResponse, RedirectResponse
from sqlalchemy.orm import Session

from service.http.deps import auth_failed, caller_of, check_auth_throttle, get_db
from service.web.deps import CSRF, get_viewer, web_signer
from service.web.render import PAGE_HEADERS, SignInRequired, render, safe_next
from svrobs_lab.auth import bearer_key
from svrobs_lab.sessions import (
    clear_cookie,
    request_session,
    set_cookie,
    sign_in,
    sign_out,
)

router = APIRouter(include_in_schema=False)


def _signed_in(request: Request, db: Session) -> bool:
    try:
        get_viewer(request, db)
    except SignInRequired:
        return False
    return True


@router.get("/session")
def session_info(request: Request, db: Annotated[Session, Depends(get_db)]):
    """``{signed_in, email, csrf}`` of the browser's session (``signed_in: false``
    without one). Same-origin pages read it: /docs sends the token with its writes."""
    try:
        viewer = get_viewer(request, db)
    except SignInRequired:
        return JSONResponse({"signed_in": False}, headers=PAGE_HEADERS)
    body = {"signed_in": True, "email": viewer.email, "csrf": viewer.csrf}
    return JSONResponse(body, headers=PAGE_HEADERS)


@router.get("/")
def home(request: Request, db: Annotated[Session, Depends(get_db)]):
    return RedirectResponse("/jobs" if _signed_in(request, db) else "/login", status_code=303)


def _login_page(request: Request, next_url: str, error: str | None = None, status: int = 200):
    """The sign-in form under the request's (anonymous) session, making one if needed."""
    signer = web_signer(request)
    ws = request_session(request)
    if ws is None or ws.signed_in:
        ws = signer.new()
    response = render(
        request,
        "login.html",
        status=status,
        viewer=None,
        csrf=signer.csrf(ws),
        next=next_url,
        error=error,
        hours=request.app.state.settings.SESSION_HOURS,
    )
    set_cookie(response, request, ws, signer)
    return response


@router.get("/login")
def login_form(request: Request, db: Annotated[Session, Depends(get_db)], next: str = "/jobs"):
    if _signed_in(request, db):
        return RedirectResponse(safe_next(next), status_code=303)
    return _login_page(request, safe_next(next))


@router.post("/login", dependencies=[CSRF])
def login(
    request: Request,
    db: Annotated[Session, Depends(get_db)],
    key: Annotated[str, Form(max_length=500)] = "",
    next: Annotated[str, Form(max_length=2000)] = "/jobs",
):
    """A valid key starts a new session (a new nonce, so a new CSRF token) holding the
    key's id; the key itself is neither stored nor echoed back. The sign-in is kept on
    the server until /logout. Too many bad keys from one address: 429
    (service.http.auth_throttle)."""
    check_auth_throttle(request)
    caller = caller_of(request, db, bearer_key(key.strip()))
    if caller is None:
        auth_failed(request)
        return _login_page(
            request, safe_next(next), "Invalid, revoked or expired API key.", status=401
        )
    signer = web_signer(request)
    response = RedirectResponse(safe_next(next), status_code=303)
    set_cookie(response, request, sign_in(db, signer, caller.key_id), signer)
    return response


@router.post("/logout", dependencies=[CSRF])
def logout(request: Request, db: Annotated[Session, Depends(get_db)]):
    """End the session on the server (a copy of the cookie stops working too)."""
    sign_out(db, request)
    response = RedirectResponse("/login", status_code=303)
    clear_cookie(response, request)
    return response
