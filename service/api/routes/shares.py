"""Share links of a job: create, list, revoke (:mod:`svrobs_lab.shares`). The link
itself, ``/s/{token}``, is a web page (service.web.pages.share) that needs no key."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from fastapi import APIRouter, Body, Path, Request, Response
from pydantic import BaseModel, Field

from service.api.deps import DB, MAX_ID, CurrentCaller, JobId, SettingsDep
from service.api.errors import error_docs
from svrobs_lab import shares
from svrobs_lab.schemas import _Strict

router = APIRouter(tags=["shares"])
ERRORS = error_docs(401, 404, 422, 429, 503)
ShareId = Annotated[int, Path(ge=1, le=MAX_ID)]


class ShareCreate(_Strict):
    days: float = Field(
        default=shares.DEFAULT_DAYS,
        ge=shares.MIN_DAYS,
        le=shares.MAX_DAYS,
        description="valid for this many days (at least one hour: 1/24)",
    )
    label: str | None = Field(
        default=None,
        max_length=shares.LABEL_MAX,
        description="what the link is for (shown in lists)",
    )


class ShareOut(BaseModel):
    id: int
    job_id: int
    created_at: datetime
    expires_at: datetime
    revoked_at: datetime | None
    label: str | None = None
    live: bool
    url: str | None = Field(None, description="the link (only in the answer that creates it)")


def share_url(request: Request, token: str) -> str:
    return str(request.base_url).rstrip("/") + f"/s/{token}"


@router.post("/jobs/{job_id}/shares", status_code=201, response_model=ShareOut, responses=ERRORS)
def create_share(
    job_id: JobId,
    request: Request,
    session: DB,
    caller: CurrentCaller,
    settings: SettingsDep,
    # None when no body is sent; not `ShareCreate | None`, which would add null to the
    # body's OpenAPI schema
    body: ShareCreate = Body(None),
):
    """A read-only link to the job's report and charts, opened without a key; it expires
    after `days` (default 7) and can be revoked. The token is shown once (only its hash
    is stored). A job has at most `SVROBS_MAX_SHARES_PER_JOB` live links (422 beyond)."""
    body = body or ShareCreate()
    link, token = shares.create(session, caller, settings, job_id, body.days, body.label)
    return shares.share_out(link, share_url(request, token))


@router.get("/jobs/{job_id}/shares", response_model=list[ShareOut], responses=ERRORS)
def list_shares(job_id: JobId, session: DB, caller: CurrentCaller):
    """The job's share links, newest first (their tokens are not kept)."""
    return [shares.share_out(s) for s in shares.job_links(session, caller, job_id)]


@router.delete("/shares/{share_id}", status_code=204, responses=ERRORS)
def revoke_share(share_id: ShareId, session: DB, caller: CurrentCaller):
    """Revoke a link: opening it is a 404 from now on."""
    shares.revoke(session, caller, share_id)
    return Response(status_code=204)
