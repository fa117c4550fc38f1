"""A dataset upload as both HTTP front ends take it (``POST /api/v1/datasets`` and the
web's ``POST /datasets/upload``): one of the process's upload slots
(:class:`~svrobs_lab.datasets.upload_slots.UploadSlots`, 429 when none is free),
the multipart body read as it arrives, its file spooled to a temporary file past
1 MiB, a 413 (PayloadTooLarge, field ``file``) as soon as it is over
SVROBS_MAX_DATASET_MB, declared or streamed; then the stored dataset
(:func:`svrobs_lab.datasets.catalog.upload`, with the team's quota) in a worker
thread. The app's in-memory body limit lets these paths through
(``service.api.mount``)."""

from __future__ import annotations

from collections.abc import Set
from functools import partial

import anyio
from fastapi import Request
from sqlalchemy.orm import Session
from starlette.datastructures import UploadFile as FormFile
from starlette.formparsers import MultiPartException, MultiPartParser

from service.http.query_text import form_without_empty_fields
from svrobs_lab.auth import Caller
from svrobs_lab.datasets.catalog import FIELDS, DatasetLimits, upload
from svrobs_lab.errors import Invalid, PayloadTooLarge

API_UPLOAD = "/api/v1/datasets"
WEB_UPLOAD = "/datasets/upload"
STREAMED = frozenset({API_UPLOAD, WEB_UPLOAD})  # POSTs past the app's body limit


async def _form(request: Request, limit: int, extra_fields: int = 0):
    """The multipart form, its file spooled to disk past 1 MiB; 413 once the body is
    over ``limit`` bytes (declared or streamed)."""
    too_big = PayloadTooLarge(
        f"the upload is over {limit // 2**20} MB (SVROBS_MAX_DATASET_MB)", field="file"
    )
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise too_big
    if not request.headers.get("content-type", "").startswith("multipart/form-data"):
        raise Invalid("send the file as multipart/form-data, in the field 'file'", field="file")

    async def counted():
        size = 0
        async for chunk in request.stream():
            size += len(chunk)
            if size > limit:
                raise too_big
            yield chunk

    parser = MultiPartParser(
        request.headers, counted(), max_files=1, max_fields=len(FIELDS) + extra_fields
    )
    try:
        return await parser.parse()
    except MultiPartException as exc:
        raise Invalid(f"not valid multipart/form-data: {exc.message}", field="file") from None


def _fields(form, ignore: Set[str], empty_is_absent: bool) -> tuple[FormFile, dict[str, str]]:
    file, fields = None, {}
    items = [(key, value) for key, value in form.multi_items() if key not in ignore]
    for key, value in form_without_empty_fields(items) if empty_is_absent else items:
        if key == "file":
            if not isinstance(value, FormFile):
                raise Invalid("must be a file, not text", field="file")
            file = value
        elif not isinstance(value, str):
            raise Invalid("must be text, not a file", field=key)
        elif key in fields:
            raise Invalid("given twice", field=key)
        else:
            fields[key] = value
    if file is None:
        raise Invalid("is required (the dataset file)", field="file")
    return file, fields


async def store_upload(
    request: Request,
    session: Session,
    caller: Caller,
    *,
    ignore: Set[str] = frozenset(),
    empty_is_absent: bool = False,
) -> dict:
    """Read the request's multipart upload (within the app settings' limits; the form
    fields in ``ignore`` left out, e.g. the web form's CSRF token; with
    ``empty_is_absent``, the web form's, an empty field is not given) and store it as
    the caller's dataset, committed -> the dataset's view. Invalid / BadDatasetFile /
    SpecError naming the field, PayloadTooLarge, RateLimited; nothing is stored then."""
    limits = DatasetLimits.of(request.app.state.settings)
    with request.app.state.upload_slots.hold(caller.team_id):
        form = await _form(request, limits.max_bytes, len(ignore))
        try:
            file, fields = _fields(form, ignore, empty_is_absent)
            store = partial(upload, session, caller, file.file, file.filename, fields, limits)
            return await anyio.to_thread.run_sync(store)
        finally:
            await form.close()
