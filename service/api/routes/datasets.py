"""Datasets of measured rollouts (docs/datasets.md#rest): upload, list, show, delete,
download; a job cell's model file; a dataset job's validation; a system object from
a system file.

The upload streams (:mod:`service.http.uploads`): the multipart body is read chunk
by chunk into a spooled temporary file (at most SVROBS_MAX_DATASET_MB, else 413 as
soon as it is over), then parsed and stored in a worker thread.
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from fastapi import APIRouter, File, Form, Path, Query, Request, Response, UploadFile
from fastapi.responses import StreamingResponse
from pydantic import BaseModel, Field

from service.api.deps import (
    DB,
    MAX_ID,
    CurrentCaller,
    JobId,
    ReportBuildsDep,
    SessionFactoryDep,
)
from service.api.errors import error_docs
from service.http.security import attachment
from service.http.uploads import store_upload
from svrobs_lab.datasets.catalog import (
    MEDIA_TYPES,
    dataset_view,
    download_name,
    file_chunks,
    list_datasets_page,
    remove_dataset,
    team_dataset,
)
from svrobs_lab.datasets.model_export import export_model
from svrobs_lab.datasets.system_file import read_system
from svrobs_lab.jobs import team_job
from svrobs_lab.validation import job_validation

router = APIRouter(tags=["datasets"])
UPLOAD_PATH = "/datasets"  # under /api/v1: service.http.uploads.API_UPLOAD
ERRORS = error_docs(401, 404, 422, 429, 503)
DatasetId = Annotated[int, Path(ge=1, le=MAX_ID, description="a dataset id of the caller's team")]

_TEXT = {"type": "string"}
UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file", "name"],
                    "properties": {
                        "file": {"type": "string", "format": "binary"},
                        "name": _TEXT,
                        "description": _TEXT,
                        "sample_time": {**_TEXT, "description": "seconds between two steps"},
                        "state_columns": {**_TEXT, "description": "CSV: x1,x2 (default x1..xn)"},
                        "input_columns": {**_TEXT, "description": "CSV: u1 (default u1..um)"},
                        "state_names": {**_TEXT, "description": "NPZ/MAT/JSON: channel names"},
                        "input_names": {**_TEXT, "description": "NPZ/MAT/JSON: channel names"},
                    },
                }
            }
        },
    }
}


class DatasetItem(BaseModel):
    id: int
    name: str
    description: str | None
    filename: str | None
    format: str
    media_type: str
    sha256: str
    arrays_sha256: str
    size_bytes: int
    n: int
    m: int
    rollouts: int
    samples: int
    T_min: int
    T_max: int
    sample_time: float | None
    state_names: list[str]
    input_names: list[str]
    owner: str | None
    created_at: datetime


class DatasetOut(DatasetItem):
    lengths: list[int]
    stats: dict[str, Any]
    excitation: dict[str, Any] | None = Field(
        None,
        description="the excitation check of all its rollouts, made at upload (null above "
        "5,000,000 numbers): eigenvalues of the regressors' mean Gram, cond, notes",
    )


class DatasetPage(BaseModel):
    items: list[DatasetItem]
    total: int
    limit: int
    offset: int


@router.post(
    UPLOAD_PATH,
    status_code=201,
    response_model=DatasetOut,
    responses={**ERRORS, **error_docs(413)},
    openapi_extra=UPLOAD_BODY,
)
async def upload_dataset(request: Request, session: DB, caller: CurrentCaller):
    """Upload a dataset file (multipart field `file`): CSV in long form, NPZ, MATLAB
    .mat (v5 or v7.3) or JSON, with a `name` and optional `description`,
    `sample_time`, `state_columns` / `input_columns` (CSV) or `state_names` /
    `input_names`. A bad file is one 422 naming the row, column or variable, and
    nothing is stored; over SVROBS_MAX_DATASET_MB is a 413."""
    body = await store_upload(request, session, caller)
    return Response(
        DatasetOut(**body).model_dump_json(),
        status_code=201,
        media_type="application/json",
        headers={"Location": f"{request.url.path}/{body['id']}"},
    )


@router.get("/datasets", response_model=DatasetPage, responses=ERRORS)
def list_datasets(
    session: DB,
    caller: CurrentCaller,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
    offset: Annotated[int, Query(ge=0, le=10**9)] = 0,
):
    """The team's datasets, newest first (without every rollout's length and the
    statistics: `GET /datasets/{id}` has them)."""
    return list_datasets_page(session, caller, limit=limit, offset=offset)


@router.get("/datasets/{dataset_id}", response_model=DatasetOut, responses=ERRORS)
def get_dataset(dataset_id: DatasetId, session: DB, caller: CurrentCaller):
    """One dataset: shapes, every rollout's length, channel names, per-channel mean,
    std, min and max, sha256 of the upload and of its arrays."""
    return dataset_view(team_dataset(session, caller, dataset_id))


@router.delete("/datasets/{dataset_id}", status_code=204, responses={**ERRORS, **error_docs(409)})
def delete_dataset(dataset_id: DatasetId, session: DB, caller: CurrentCaller):
    """Delete a dataset with its stored bytes; 409 naming the jobs that use it."""
    remove_dataset(session, caller, dataset_id)  # NotFound: 404, DatasetInUse: 409
    return Response(status_code=204)


@router.get(
    "/datasets/{dataset_id}/file",
    responses={**ERRORS, 200: {"content": {"application/octet-stream": {}}}},
)
def download_dataset(
    dataset_id: DatasetId, session: DB, caller: CurrentCaller, session_factory: SessionFactoryDep
):
    """The file as it was uploaded (byte for byte: its sha256 is the dataset's), with
    its media type and file name."""
    row = team_dataset(session, caller, dataset_id)
    name, size, media = download_name(row), row.size_bytes, MEDIA_TYPES[row.format]
    session.close()  # the stream reads with a session of its own

    return StreamingResponse(
        file_chunks(session_factory, dataset_id),
        media_type=media,
        headers={
            "Content-Disposition": attachment(name),
            "Content-Length": str(size),
            "ETag": f'"{row.sha256}"',
        },
    )


@router.get(
    "/jobs/{job_id}/model",
    tags=["models"],
    responses={
        **ERRORS,
        **error_docs(409, 410),
        200: {"content": {"application/json": {}, "application/octet-stream": {}}},
    },
)
def get_model(
    job_id: JobId,
    session: DB,
    caller: CurrentCaller,
    cell: Annotated[
        str | None,
        Query(
            max_length=2000,
            description="system=S,sigma_w=W,N=50,estimator=svr,gamma=0.05,rep=0 "
            "(any subset that picks one cell; gamma=null for ols), or a JSON object",
        ),
    ] = None,
    format: Literal["json", "npz", "mat"] = "json",
):
    """One cell of the job as a model file: A_hat, B_hat, C, the radii and eps, L with
    g(L), K, delta, sigma_w, and the provenance (dataset sha256, spec, version). 409
    when the job is queued or running and no computed cell matches yet; 410 once
    retention dropped the job's cell rows."""
    job = team_job(session, caller, job_id)
    content, media, name = export_model(session, job, cell=cell, fmt=format)
    return Response(content, media_type=media, headers={"Content-Disposition": attachment(name)})


@router.get("/jobs/{job_id}/validation", tags=["models"], responses=ERRORS)
def get_validation(
    job_id: JobId,
    session: DB,
    caller: CurrentCaller,
    session_factory: SessionFactoryDep,
    builds: ReportBuildsDep,
) -> dict:
    """A dataset job's validation on its held-out rollouts (docs/measured.md#validation):
    per estimator and gamma, the model fitted on the largest N's training rollouts,
    one-step and simulation fit per channel, Ljung-Box and input-residual
    cross-correlation tests with their p-values, the residual autocorrelation with its
    band; the excitation check of those rollouts; the measured and predicted series of
    the first held-out rollouts (for plots). Computed once and stored (one computation
    per job at a time; 429 with Retry-After while the team builds too many reports or
    validations); 404 for a job that is not on a dataset."""
    return job_validation(session, caller, job_id, session_factory, builds=builds)


@router.post("/systems/from-file", tags=["presets"], responses={**ERRORS, **error_docs(413)})
def system_from_file(
    caller: CurrentCaller,
    file: Annotated[UploadFile, File(description="NPZ, .mat or JSON with A, B, optionally C")],
    name: Annotated[str | None, Form(max_length=64)] = None,
) -> dict:
    """A custom system for a spec's `systems` list from a file holding `A`, `B` and
    optionally `C`, `sigma_u`, `sigma_v` (checked as a spec's system is)."""
    return read_system(file.file, filename=file.filename, name=name)
