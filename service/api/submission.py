"""Submit and publish: the one path by which a route creates jobs (``POST /jobs``, the
paper preset).

The jobs and their work units are inserted and committed in the request's
transaction; only then, after the response, are the new units sent to the broker
(:func:`publish_after_commit`). Nothing is lost if publishing fails: the relay
(beat) re-publishes units never marked published. Bad specs, the team's quota and a
reused Idempotency-Key raise the DB package's errors, which
:mod:`service.api.errors` maps to 422 / 429 / 409.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Annotated

from fastapi import BackgroundTasks, Depends

from service.api.deps import (
    DB,
    CurrentCaller,
    Publisher,
    PublisherDep,
    SessionFactory,
    SessionFactoryDep,
    SettingsDep,
)
from service.api.views import job_out
from service.db.jobs import create_job, unit_ids_of_job
from service.db.outbox import mark_published

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class JobRequest:
    """One job to create: a SPEC section 10 spec and its labels."""

    spec: dict
    name: str | None = None
    tags: Iterable[str] = ()
    idempotency_key: str | None = None


class Submission:
    """The submit-and-publish step of one request, a FastAPI dependency
    (:data:`SubmissionDep`) built from the request's session, caller and settings."""

    def __init__(
        self,
        *,
        session: DB,
        caller: CurrentCaller,
        settings: SettingsDep,
        publisher: PublisherDep,
        session_factory: SessionFactoryDep,
        background: BackgroundTasks,
    ):
        self.session, self.caller, self.settings = session, caller, settings
        self.publisher, self.session_factory = publisher, session_factory
        self.background = background

    def submit(self, requests: Sequence[JobRequest]) -> list[dict]:
        """Create the jobs (or find them by Idempotency-Key), commit, and schedule the
        publishing of the new ones' units after the response; returns the jobs' bodies."""
        session, caller, settings = self.session, self.caller, self.settings
        bodies, unit_ids = [], []
        for r in requests:
            job, created = create_job(
                session,
                team_id=caller.team_id,
                user_id=caller.user_id,
                spec=r.spec,
                name=r.name,
                tags=r.tags,
                idempotency_key=r.idempotency_key,
                max_cells=settings.MAX_JOB_CELLS,
                max_active_jobs=settings.MAX_QUEUED_JOBS_PER_TEAM,
            )
            if created:
                unit_ids += unit_ids_of_job(session, job.id)
            bodies.append(job_out(job))  # flushed: ids and defaults are set; no read-back
        session.commit()
        session.close()  # end this request's transaction before publishing
        if unit_ids:
            self.background.add_task(
                publish_after_commit, self.publisher, self.session_factory, unit_ids
            )
        return bodies


SubmissionDep = Annotated[Submission, Depends(Submission)]


def publish_after_commit(
    publisher: Publisher, session_factory: SessionFactory, unit_ids: list[int]
) -> None:
    """Send the committed units to the broker and mark them published."""
    try:
        sent = publisher(unit_ids)
    except Exception as exc:  # pragma: no cover - publishers catch their own errors
        log.warning("publishing failed: %s", exc)
        return
    if not sent:
        return
    try:
        session = session_factory(True)
        try:
            mark_published(session, sent)
            session.commit()
        finally:
            session.close()
    except Exception as exc:
        log.warning("marking %d units published failed: %s", len(sent), exc)
