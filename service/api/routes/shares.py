"""Share links of a job (issue 11): create, list, revoke. The link itself, ``/s/{token}``,
is a web page (service.web.pages.share) that needs no key."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from fastapi import APIRouter, HTTPException, Path, Request, Response
from pydantic import BaseModel, ConfigDict, Field

from service.api.deps import DB, MAX_ID, CurrentCaller, JobId, team_job
from service.api.errors import error_docs
from service.db import shares

router = APIRouter(tags=["shares"])
ERRORS = error_docs(401, 404, 422, 429, 503)
ShareId = Annotated[int, Path(ge=1, le=MAX_ID)]


class ShareCreate(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    days: float = Field(
        shares.DEFAULT_DAYS, gt=0, le=shares.MAX_DAYS, description="valid for this many days"
    )


class ShareOut(BaseModel):
    id: int
    job_id: int
    created_at: datetime
    expires_at: datetime
    revoked_at: datetime | None
    live: bool
    url: str | None = Field(None, description="the link (only in the answer that creates it)")


def share_out(link, url: str | None = None) -> dict:
    return {
        "id": link.id,
        "job_id": link.job_id,
        "created_at": link.created_at,
        "expires_at": link.expires_at,
        "revoked_at": link.revoked_at,
        "live": shares.is_live(link),
        "url": url,
    }


def share_url(request: Request, token: str) -> str:
    return str(request.base_url).rstrip("/") + f"/s/{token}"


@router.post("/jobs/{job_id}/shares", status_code=201, response_model=ShareOut, responses=ERRORS)
def create_share(
    job_id: JobId, request: Request, session: DB, caller: CurrentCaller, body: ShareCreate = None
):
    """A read-only link to the job's report and charts, opened without a key; it expires
    after `days` (default 7) and can be revoked. The token is shown once (only its hash
    is stored)."""
    job = team_job(session, caller.team_id, job_id)
    link, token = shares.create_share(
        session, job, user_id=caller.user_id, days=(body or ShareCreate()).days
    )
    session.commit()
    return share_out(link, share_url(request, token))


@router.get("/jobs/{job_id}/shares", response_model=list[ShareOut], responses=ERRORS)
def list_shares(job_id: JobId, session: DB, caller: CurrentCaller):
    """The job's share links, newest first (their tokens are not kept)."""
    team_job(session, caller.team_id, job_id)
    return [share_out(s) for s in shares.job_shares(session, caller.team_id, job_id)]


@router.delete("/shares/{share_id}", status_code=204, responses=ERRORS)
def revoke_share(share_id: ShareId, session: DB, caller: CurrentCaller):
    """Revoke a link: opening it is a 404 from now on."""
    link = shares.team_share(session, caller.team_id, share_id)
    if link is None:
        raise HTTPException(404, f"share link {share_id} not found")
    shares.revoke_share(link)
    session.commit()
    return Response(status_code=204)
