"""The limit on a request's body, for the API and the pages alike
(``SVROBS_MAX_BODY_BYTES``); :mod:`service.app` says how each answers it."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from service.http.uploads import STREAMED

# (scope, status, message) -> the ASGI app that answers it
Respond = Callable[[dict[str, Any], int, str], Any]


class BodyLimitMiddleware:
    """413 for a request body over ``max_bytes`` (declared Content-Length or streamed),
    answered by ``respond(scope, status, message)`` (the API's JSON or the web's page).
    A dataset upload (the API's and the web's) is streamed by its route under its own
    limit, SVROBS_MAX_DATASET_MB (:mod:`service.http.uploads`), so it passes here."""

    def __init__(self, app, max_bytes: int, respond: Respond):
        self.app = app
        self.max_bytes = max_bytes
        self.respond = respond

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS", "DELETE"):
            return await self.app(scope, receive, send)
        if scope["path"] in STREAMED:  # streamed by its route, under its own limit
            return await self.app(scope, receive, send)
        too_big = self.respond(
            scope, 413, f"request body over {self.max_bytes} bytes (SVROBS_MAX_BODY_BYTES)"
        )
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    if int(value) > self.max_bytes:
                        return await too_big(scope, receive, send)
                except ValueError:
                    bad = self.respond(scope, 400, "bad Content-Length")
                    return await bad(scope, receive, send)
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
