"""The REST API under /api/v1 (and /healthz, /readyz): ``mount_api(app)`` adds its
routers, its request rules, its error mapping (:mod:`service.api.errors`) and the
slots of its results streams (:mod:`svrobs_lab.slots`) to the app that
:mod:`service.app` builds."""

from __future__ import annotations

from fastapi import Depends, FastAPI

from service.api.docs import install_redoc, install_swagger
from service.api.errors import error_response
from service.api.query_params import reject_unknown_query
from service.http.query_text import clean_query_text
from service.http.uploads import STREAMED
from svrobs_lab.slots import stream_slots

API_PREFIX = "/api/v1"


class BodyLimitMiddleware:
    """413 for a request body over ``max_bytes`` (declared Content-Length or streamed).
    A dataset upload (the API's and the web's) is streamed by its route under its own
    limit, SVROBS_MAX_DATASET_MB (:mod:`service.http.uploads`), so it passes here."""

    def __init__(self, app, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS", "DELETE"):
            return await self.app(scope, receive, send)
        if scope["path"] in STREAMED:  # streamed by its route, under its own limit
            return await self.app(scope, receive, send)
        too_big = error_response(
            413, f"request body over {self.max_bytes} bytes (SVROBS_MAX_BODY_BYTES)"
        )
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    if int(value) > self.max_bytes:
                        return await too_big(scope, receive, send)
                except ValueError:
                    return await error_response(400, "bad Content-Length")(scope, receive, send)
        # Read (at most max_bytes + 1) and replay, so a lying or absent length is caught too.
        chunks, size, more = [], 0, True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            body = message.get("body", b"")
            size += len(body)
            if size > self.max_bytes:
                return await too_big(scope, receive, send)
            chunks.append(body)
            more = message.get("more_body", False)
        data = b"".join(chunks)
        sent = False

        async def replay():
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": data, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


def mount_api(app: FastAPI) -> None:
    """Serve the API's routes on ``app`` (its settings set), with ReDoc and the body limit."""
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
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.MAX_BODY_BYTES)
