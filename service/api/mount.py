"""The REST API under /api/v1 (and /healthz, /readyz): ``mount_api(app)`` adds its
routers, its request rules (query text, unknown parameters), its documentation pages
and the slots of its results streams (:mod:`svrobs_lab.slots`) to the app that
:mod:`service.app` builds; :mod:`service.app` installs the error mapping
(:mod:`service.api.errors`)."""

from __future__ import annotations

from fastapi import Depends, FastAPI

from service.api.docs import install_redoc, install_swagger
from service.api.query_params import reject_unknown_query
from service.http.query_text import clean_query_text
from svrobs_lab.slots import stream_slots

API_PREFIX = "/api/v1"


def mount_api(app: FastAPI) -> None:
    """Serve the API's routes on ``app`` (its settings set), with ReDoc."""
    from service.api.routes import (
        datasets,
        health,
        jobs,
        presets,
        reports,
        results,
        schedules,
        shares,
    )

    install_redoc(app)
    install_swagger(app)
    settings = app.state.settings
    # results streamed at once, each holding a database connection (svrobs_lab.slots)
    app.state.stream_slots = stream_slots(
        per_team=settings.STREAMS_PER_TEAM, at_once=settings.STREAMS_AT_ONCE
    )
    query_rules = [Depends(clean_query_text), Depends(reject_unknown_query)]
    app.include_router(health.router, dependencies=query_rules[1:])
    for module in (jobs, results, presets, reports, schedules, shares, datasets):
        app.include_router(module.router, prefix=API_PREFIX, dependencies=query_rules)
