"""FastAPI dependencies of the REST API: the caller of a bearer key (or the web
session's: for a read, or a write that carries the session's CSRF token, as the API
docs page sends it), a submission of the caller. The ones the web shares (DB
sessions, settings, the publisher, the query-text rule) are in :mod:`service.http`."""

from __future__ import annotations

from typing import Annotated

from fastapi import BackgroundTasks, Depends, HTTPException, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from service.http.deps import (
    DB,
    BrokerCheckDep,
    PublisherDep,
    ReportBuildsDep,
    SessionFactoryDep,
    SettingsDep,
    auth_failed,
    caller_of,
    check_auth_throttle,
    get_db,
    is_write,
    rate_limit,
    submission_of,
)
from svrobs_lab.auth import MAX_ID, Caller, bearer_key
from svrobs_lab.jobs import Submission
from svrobs_lab.sessions import request_session, session_key, signer_of

JobId = Annotated[int, Path(ge=1, le=MAX_ID, description="a job id of the caller's team")]


def _unauthorized(detail: str) -> HTTPException:
    return HTTPException(401, detail, headers={"WWW-Authenticate": "Bearer"})


# declares the scheme in OpenAPI (the Authorize button of /docs); the header is read
# below, so a missing or malformed one keeps this module's 401 bodies
BEARER = HTTPBearer(auto_error=False, description="an API key: `Authorization: Bearer <key>`")


def get_caller(
    request: Request,
    session: Annotated[Session, Depends(get_db)],
    _bearer: Annotated[HTTPAuthorizationCredentials | None, Depends(BEARER)] = None,
) -> Caller:
    """The bearer key's caller. A reading request (GET) without an Authorization
    header may instead carry the web UI's session cookie (svrobs_lab.sessions), so
    that a signed-in browser opens reports and downloads; a write only with the
    session's CSRF token in ``X-CSRF-Token`` too (what the dashboard's forms need;
    /docs sends it), so that no other site can make a signed-in browser write. A bad
    bearer key counts against the client's address (service.http.auth_throttle)."""
    header = request.headers.get("authorization", "")
    scheme, _, token = header.partition(" ")
    if not header and (not is_write(request) or _session_csrf_ok(request)):
        caller = caller_of(request, session, lambda s: session_key(request, s))
        if caller is None:
            raise _unauthorized("missing API key: send 'Authorization: Bearer <key>'")
    elif scheme.lower() != "bearer" or not token.strip():
        raise _unauthorized("missing API key: send 'Authorization: Bearer <key>'")
    else:
        check_auth_throttle(request)  # 429 after too many bad keys from this address
        caller = caller_of(request, session, bearer_key(token.strip()))
        if caller is None:
            auth_failed(request)
            raise _unauthorized("invalid, revoked or expired API key")
    rate_limit(request, caller)
    return caller


def _session_csrf_ok(request: Request) -> bool:
    signer = signer_of(request.app)
    token = request.headers.get("x-csrf-token")
    return signer is not None and signer.csrf_ok(request_session(request), token)


CurrentCaller = Annotated[Caller, Depends(get_caller)]


def get_submission(
    request: Request, session: DB, caller: CurrentCaller, background: BackgroundTasks
) -> Submission:
    return submission_of(request, session, caller, background)


SubmissionDep = Annotated[Submission, Depends(get_submission)]

__all__ = [
    "DB",
    "MAX_ID",
    "BrokerCheckDep",
    "CurrentCaller",
    "JobId",
    "PublisherDep",
    "ReportBuildsDep",
    "SessionFactoryDep",
    "SettingsDep",
    "SubmissionDep",
    "get_caller",
]
