"""``/datasets``: the team's datasets and an upload form whose file goes up with a
progress bar (XMLHttpRequest to ``POST /datasets/upload``, streamed as the API's
upload is: :mod:`service.http.uploads`); ``/datasets/{id}``: one dataset's facts,
statistics, excitation check, a plot of its first rollouts per channel and "new job
on this dataset". Everything comes from :mod:`svrobs_lab.datasets.overview`; another
team's dataset is a 404 page."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse
from sqlalchemy.orm import Session

from service.http.deps import get_db
from service.http.errors import status_of
from service.http.uploads import WEB_UPLOAD, store_upload
from service.web.deps import CurrentViewer, check_csrf
from service.web.render import PAGE_HEADERS, WebError, render
from svrobs_core.errors import SpecError
from svrobs_lab.auth import MAX_ID
from svrobs_lab.datasets import overview
from svrobs_lab.errors import LabError

router = APIRouter(include_in_schema=False)
DB = Annotated[Session, Depends(get_db)]


def _id(dataset_id: int) -> int:
    if not 1 <= dataset_id <= MAX_ID:
        raise WebError(404, f"Dataset {dataset_id} not found.")
    return dataset_id


@router.get("/datasets")
def datasets_page(request: Request, db: DB, viewer: CurrentViewer):
    page = overview.datasets_page(db, viewer.caller)
    return render(
        request,
        "datasets.html",
        viewer=viewer,
        nav="datasets",
        page=page,
        limit_mb=request.app.state.settings.MAX_DATASET_MB,
        upload_url=WEB_UPLOAD,
    )


@router.post(WEB_UPLOAD)
async def upload(request: Request, db: DB, viewer: CurrentViewer):
    """The upload form's file (the CSRF token in the X-CSRF-Token header, so that the
    body is read only as it streams) -> 201 ``{"id", "url"}``, or the error as JSON
    ``{"detail", "field"}`` for the form to show beside its field. An empty field is
    not given (an empty "CSV input columns": the columns u1..um, not no inputs)."""
    check_csrf(request, None, request.headers.get("x-csrf-token"))
    try:
        body = await store_upload(
            request, db, viewer.caller, ignore={"csrf_token"}, empty_is_absent=True
        )
    except (LabError, SpecError) as exc:  # shown in place by the form
        return JSONResponse(
            {"detail": exc.message, "field": exc.field},
            status_code=status_of(exc),
            headers=PAGE_HEADERS,
        )
    url = f"/datasets/{body['id']}"
    return JSONResponse({"id": body["id"], "url": url}, status_code=201, headers=PAGE_HEADERS)


@router.get("/datasets/{dataset_id:int}")
def dataset_page(request: Request, db: DB, viewer: CurrentViewer, dataset_id: int):
    info = overview.dataset_overview(db, viewer.caller, _id(dataset_id))
    return render(request, "dataset.html", viewer=viewer, nav="datasets", **info)


@router.get("/datasets/{dataset_id:int}/plot-data")
def plot_data(db: DB, viewer: CurrentViewer, dataset_id: int):
    """The first rollouts of the dataset, for its page's plot."""
    data = overview.plot_data(db, viewer.caller, _id(dataset_id))
    return JSONResponse(data, headers=PAGE_HEADERS)
