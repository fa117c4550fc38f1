"""Submit and publish: the one path by which a route creates jobs (``POST /jobs``, the
paper preset).

The jobs and their work units are inserted and committed in the request's
transaction; only then, after the response, are the team's next units sent to the
broker within its fair share (:func:`dispatch_after_commit`,
:func:`service.db.outbox.dispatch`); the rest follow as its units finish. Nothing is
lost if publishing fails: the relay (beat) publishes units never marked published. Bad specs, the team's quota and a
reused Idempotency-Key raise the DB package's errors, which
:mod:`service.api.errors` maps to 422 / 429 / 409.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from contextlib import contextmanager
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
from service.db.jobs import create_job
from service.db.outbox import dispatch

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
        bodies, created_any = [], False
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
                max_cpu_seconds=settings.MAX_JOB_CPU_SECONDS,
                max_unit_mb=settings.MAX_UNIT_MEMORY_MB,
                max_active_jobs=settings.MAX_QUEUED_JOBS_PER_TEAM,
            )
            created_any |= created
            bodies.append(job_out(job))  # flushed: ids and defaults are set; no read-back
        session.commit()
        session.close()  # end this request's transaction before publishing
        if created_any:
            self.dispatch_after_response()
        return bodies

    def dispatch_after_response(self) -> None:
        """Publish the team's next units (its fair share) once the response is sent
        (after a submission, or a cancel that freed the team's slots). The request's
        session must be closed first (SQLite: its write lock)."""
        self.background.add_task(
            dispatch_after_commit,
            self.publisher,
            self.session_factory,
            self.caller.team_id,
            self.settings.MAX_UNITS_IN_FLIGHT_PER_TEAM,
        )


SubmissionDep = Annotated[Submission, Depends(Submission)]


def dispatch_after_commit(
    publisher: Publisher, session_factory: SessionFactory, team_id: int, cap: int
) -> None:
    """Send the team's next units to the broker (within its fair share ``cap``) and
    mark them published; what fails is left to the relay."""

    @contextmanager
    def begin():
        session = session_factory(True)
        try:
            yield session
            session.commit()
        finally:
            session.close()

    try:
        dispatch(begin, publisher, team_id=team_id, cap=cap)
    except Exception as exc:
        log.warning("publishing the units of team %s failed: %s", team_id, exc)
