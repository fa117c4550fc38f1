"""The web UI: server-rendered pages (Jinja2 + htmx + Chart.js, all served from
``static/``) behind a sign-in with an API key; see :mod:`svrobs_lab.sessions` for the
cookie and CSRF rules. ``mount_web(app)`` adds it to the app of :mod:`service.app`.

A page module under ``pages/`` has a ``router``, included by ``mount_web``. Its
routes take ``deps.CurrentViewer`` (the signed-in viewer, else a redirect to
/login), state-changing ones ``dependencies=[deps.CSRF]``; they answer with
``render.render(request, template, viewer=viewer, ...)`` (templates extend
``base.html``) and raise ``render.WebError(404, ...)`` for another team's object;
an application error they let through is a page too (:mod:`service.web.errors`).
"""

from __future__ import annotations

from fastapi import Depends, FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from service.http.errors import ErrorHandler
from service.http.query_text import clean_page_query
from service.web.render import STATIC, SignInRequired, WebError, sign_in_redirect, web_error_page
from svrobs_lab.sessions import Signer, load_secret


def mount_web(app: FastAPI) -> None:
    """Serve the pages, ``/static`` and the error pages on ``app`` (its settings set)."""
    from service.web.pages import (  # a new page module: add it here
        auth,
        cell,
        compare,
        datasets,
        job,
        jobs,
        results,
        schedules,
        share,
        submit,
    )

    settings = app.state.settings
    app.state.web_signer = Signer(load_secret(settings), session_hours=settings.SESSION_HOURS)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    app.add_api_route("/favicon.ico", _favicon, include_in_schema=False)
    for module in (auth, jobs, submit, job, results, cell, compare, schedules, share, datasets):
        # the API's query-text rule (NUL, plain numbers), an empty form field no value
        app.include_router(module.router, dependencies=[Depends(clean_page_query)])
    handlers: tuple[tuple[type[Exception], ErrorHandler], ...] = (
        (WebError, web_error_page),
        (SignInRequired, sign_in_redirect),
    )
    for exc_class, handler in handlers:
        app.add_exception_handler(exc_class, handler)


def _favicon() -> FileResponse:
    """The icon browsers ask for at /favicon.ico (pages link /static/favicon.svg)."""
    return FileResponse(STATIC / "favicon.ico", media_type="image/x-icon")
