"""The jobs a page offers to pick from (the compare page's checkboxes, the job list of
the results page and of a new schedule): the team's newest jobs, and before them each
chosen job that is older than those (a run ticked in the runs table, a job whose page
the schedule or results link came from), so a chosen job is always listed as chosen."""

from __future__ import annotations

from collections.abc import Iterable
from typing import NamedTuple

from sqlalchemy.orm import Session

from service.db import job_queries as queries
from service.db.models import Job
from svrobs_lab.auth import MAX_ID

NEWEST = 200  # the newest jobs listed


class Picks(NamedTuple):
    jobs: list[Job]  # the chosen older jobs, then the newest
    older: int  # how many chosen jobs are older than the newest listed


def job_picks(db: Session, viewer, chosen: Iterable[int] = ()) -> Picks:
    """The team's ``NEWEST`` newest jobs, after the chosen ones not among them."""
    newest, _ = queries.job_page(
        db, viewer.team_id, viewer.caller.user_id, queries.JobFilter(), limit=NEWEST, offset=0
    )
    listed = {j.id for j in newest}
    older = []
    for job_id in dict.fromkeys(chosen):
        if job_id in listed or not 1 <= job_id <= MAX_ID:
            continue
        job = queries.team_job(db, viewer.team_id, job_id)
        if job is not None:
            older.append(job)
    return Picks(older + newest, len(older))
