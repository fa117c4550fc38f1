"""The dataset use cases (docs/datasets.md): upload (check the fields, parse the
file, check the team's dataset quota, store the row, the original bytes and the
arrays in the caller's transaction), find, describe and delete a team's datasets.

Nothing is written before the file has been read whole and found good and the
team's quota has room for it, so a refused file leaves no row and no chunk. The
caller commits.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterator, Mapping
from contextlib import closing
from dataclasses import dataclass
from typing import BinaryIO, cast

from sqlalchemy.orm import Session

from service.db import datasets as store
from service.db.models import Dataset
from service.db.quota import lock_team_quota
from svrobs_core.errors import SpecError
from svrobs_core.measured import regressor_excitation
from svrobs_core.text import NOT_PRINTABLE, printable, strip_unprintable

from .. import json_text
from ..auth import Caller
from ..dispatch import SessionFactory
from ..errors import DatasetNotFound, Invalid, NotFound
from .parsed import DatasetOptions, ParsedDataset, name_refused
from .reader import parse_dataset
from .stacked import regressors

FIELDS = (
    "name",
    "description",
    "sample_time",
    "state_columns",
    "input_columns",
    "state_names",
    "input_names",
)
MAX_DESCRIPTION = 4000
MEDIA_TYPES = {
    "csv": "text/csv",
    "json": "application/json",
    "npz": "application/octet-stream",
    "mat": "application/x-matlab-data",
    "mat73": "application/x-matlab-data",
}
# the excitation check is made at upload for datasets of up to this many numbers (about
# 40 MB of float64 arrays, and their regression copies); a job's validation has it for any
EXCITATION_MAX_VALUES = 5_000_000
_FLOAT_TEXT = re.compile(r"-?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?", re.ASCII)
_LINE_BREAKS = str.maketrans("", "", "\t\r\n")  # a description's tabs and line breaks


def _text(fields: Mapping, key: str, *, limit: int, required: bool = False) -> str | None:
    """A text field: printable (docs/security.md#names-in-downloads-and-pages), but for
    the tabs and line breaks of a description."""
    value = fields.get(key)
    if value is None or not value.strip():
        if required:
            raise SpecError(key, "is required")
        return None
    value = value.strip()
    if len(value) > limit:
        raise SpecError(key, f"at most {limit} characters")
    if not printable(value.translate(_LINE_BREAKS) if key == "description" else value):
        raise SpecError(key, NOT_PRINTABLE)
    return value


def _name_list(fields: Mapping, key: str) -> tuple[str, ...] | None:
    """A list field: comma-separated, or a JSON list of strings; "" is the empty list."""
    value = fields.get(key)
    if value is None:
        return None
    value = value.strip()
    if value.startswith("["):
        try:
            items = json_text.loads(value)
        except ValueError:
            raise SpecError(key, "not a JSON list of strings") from None
        if not isinstance(items, list) or not all(isinstance(v, str) for v in items):
            raise SpecError(key, "not a JSON list of strings")
    else:
        items = value.split(",") if value else []
    items = [v.strip() for v in items]
    if any(not v for v in items):
        raise SpecError(key, "has an empty name (two commas in a row?)")
    unprintable = next((v for v in items if not printable(v)), None)
    if unprintable is not None:
        raise SpecError(key, name_refused(unprintable))
    if len(items) > 50:
        raise SpecError(key, f"{len(items)} names; at most 50")
    return tuple(items)


def _sample_time(fields: Mapping) -> float | None:
    value = fields.get("sample_time")
    if value is None or not value.strip():
        return None
    if not _FLOAT_TEXT.fullmatch(value.strip()):
        raise SpecError("sample_time", f"{value.strip()!r} is not a number")
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise SpecError("sample_time", "must be a positive finite number (seconds)")
    return v


def check_fields(fields: Mapping[str, str | None]) -> tuple[str, str | None, DatasetOptions]:
    """(name, description, options) of an upload's form fields; SpecError naming the
    field for an unknown or bad one."""
    unknown = next((k for k in fields if k not in FIELDS), None)
    if unknown is not None:
        raise SpecError(unknown, "unknown field")
    name = _text(fields, "name", limit=200, required=True)
    description = _text(fields, "description", limit=MAX_DESCRIPTION)
    state_columns = _name_list(fields, "state_columns")
    if state_columns == ():
        raise SpecError("state_columns", "name at least one state column")
    state_names = _name_list(fields, "state_names")
    if state_names == ():
        raise SpecError("state_names", "name at least one state")
    options = DatasetOptions(
        state_columns=state_columns,
        input_columns=_name_list(fields, "input_columns"),
        state_names=state_names,
        input_names=_name_list(fields, "input_names"),
        sample_time=_sample_time(fields),
    )
    return cast(str, name), description, options  # required: a str


def clean_filename(filename: str | None) -> str | None:
    """The upload's file name without folders or the characters a name may not hold
    (docs/security.md#names-in-downloads-and-pages), at most 255 characters."""
    if not filename:
        return None
    base = os.path.basename(filename.replace("\\", "/"))
    base = strip_unprintable(base).strip()[:255]
    return base or None


def _file_chunks(stream: BinaryIO) -> Iterator[bytes]:
    stream.seek(0)
    while chunk := stream.read(store.CHUNK_BYTES):
        yield chunk


@dataclass(frozen=True, kw_only=True)
class DatasetLimits:
    """An upload's limits (docs/datasets.md#limits): ``max_bytes`` of the file (and
    what it may read), and the team's quota: at most ``max_datasets`` datasets
    holding at most ``max_team_bytes`` (None or 0: no cap)."""

    max_bytes: int
    max_datasets: int | None = None
    max_team_bytes: int | None = None

    @classmethod
    def of(cls, settings) -> DatasetLimits:
        """The limits of the service's settings."""
        return cls(
            max_bytes=settings.MAX_DATASET_MB * 2**20,
            max_datasets=settings.MAX_DATASETS_PER_TEAM,
            max_team_bytes=settings.MAX_TEAM_DATASETS_MB * 2**20,
        )


def check_team_quota(
    session: Session, team_id: int, parsed: ParsedDataset, limits: DatasetLimits
) -> None:
    """Invalid (field ``file``) when the team's datasets, with this one, would be more
    than ``limits`` allow. Holds the team's quota lock until the transaction ends,
    so that concurrent uploads are counted one after the other."""
    if not limits.max_datasets and not limits.max_team_bytes:
        return
    lock_team_quota(session, team_id)
    count, held = store.team_usage(session, team_id)
    if limits.max_datasets and count >= limits.max_datasets:
        raise Invalid(
            f"the team has {count} datasets; the limit is {limits.max_datasets} "
            "(SVROBS_MAX_DATASETS_PER_TEAM): delete one first",
            field="file",
        )
    size = store.stored_bytes(
        parsed.n, parsed.m, parsed.rollouts, parsed.samples, parsed.size_bytes
    )
    if limits.max_team_bytes and held + size > limits.max_team_bytes:
        mb = 2**20
        raise Invalid(
            f"the team's datasets hold {held / mb:,.1f} MB and this one would add "
            f"{size / mb:,.1f} MB (its file and its arrays); the limit is "
            f"{limits.max_team_bytes // mb:,} MB (SVROBS_MAX_TEAM_DATASETS_MB)",
            field="file",
        )


def upload_excitation(parsed: ParsedDataset) -> dict | None:
    """The excitation check of all the parsed rollouts as stored with the dataset, or
    None above EXCITATION_MAX_VALUES numbers: that of their MeasuredData, made of
    the stacked rollouts (no array a rollout)."""
    values = store.array_values(parsed.n, parsed.m, parsed.rollouts, parsed.samples)
    if values > EXCITATION_MAX_VALUES:
        return None
    names = tuple(parsed.state_names) + tuple(parsed.input_names)
    return regressor_excitation(regressors(parsed.X, parsed.U), names).to_dict()


def create_dataset(
    session: Session,
    *,
    team_id: int,
    user_id: int | None,
    stream: BinaryIO,
    filename: str | None,
    fields: Mapping[str, str | None],
    limits: DatasetLimits,
) -> Dataset:
    """Check the fields, parse the file (a seekable binary stream), check the team's
    quota and store the dataset with its original bytes, its arrays and its
    excitation check (flushed, not committed). Raises BadDatasetFile (field
    ``file``), Invalid (the quota) or SpecError naming the field; nothing is written
    then."""
    name, description, options = check_fields(fields)
    filename = clean_filename(filename)
    parsed = parse_dataset(stream, filename=filename, options=options, max_bytes=limits.max_bytes)
    checked = upload_excitation(parsed)
    check_team_quota(session, team_id, parsed, limits)
    arrays = parsed.arrays()
    lengths = parsed.lengths
    row = store.add_dataset(
        session,
        team_id=team_id,
        user_id=user_id,
        name=name,
        description=description,
        filename=filename,
        format=parsed.format,
        sha256=parsed.sha256,
        arrays_sha256=store.arrays_digest(arrays),
        size_bytes=parsed.size_bytes,
        n=parsed.n,
        m=parsed.m,
        rollouts=parsed.rollouts,
        samples=parsed.samples,
        t_min=min(lengths),
        t_max=max(lengths),
        lengths=lengths,
        sample_time=parsed.sample_time,
        state_names=parsed.state_names,
        input_names=parsed.input_names,
        stats=parsed.stats,
        excitation=checked,
    )
    store.add_chunks(session, row.id, "file", _file_chunks(stream))
    store.add_chunks(session, row.id, "arrays", store.array_chunks(arrays))
    session.flush()
    return row


def upload(
    session: Session,
    caller: Caller,
    stream: BinaryIO,
    filename: str | None,
    fields: Mapping[str, str | None],
    limits: DatasetLimits,
) -> dict:
    """:func:`create_dataset` for the caller, committed -> the dataset as the API
    answers it."""
    row = create_dataset(
        session,
        team_id=caller.team_id,
        user_id=caller.user_id,
        stream=stream,
        filename=filename,
        fields=fields,
        limits=limits,
    )
    session.commit()
    return dataset_view(team_dataset(session, caller, row.id))


def resolve_dataset(session: Session, team_id: int, dataset_id: int) -> Dataset:
    """The team's dataset ``dataset_id``; DatasetNotFound naming the spec field
    ``dataset`` when the team has none of that id (another team's included)."""
    row = store.team_dataset(session, team_id, dataset_id)
    if row is None:
        raise DatasetNotFound(dataset_id, "dataset")
    return row


def team_dataset(session: Session, caller: Caller, dataset_id: int) -> Dataset:
    """The caller's dataset, or NotFound (another team's is indistinguishable from none)."""
    row = store.team_dataset(session, caller.team_id, dataset_id)
    if row is None:
        raise NotFound(f"dataset {dataset_id} not found")
    return row


def list_datasets_page(session: Session, caller: Caller, *, limit: int, offset: int) -> dict:
    """One page of the team's datasets, newest first, without every rollout's length
    and the statistics, with the total."""
    rows, total = store.list_datasets(session, caller.team_id, limit=limit, offset=offset)
    items = [dataset_view(r, full=False) for r in rows]
    return {"items": items, "total": total, "limit": limit, "offset": offset}


def remove_dataset(session: Session, caller: Caller, dataset_id: int) -> None:
    """Delete the caller's dataset, committed: NotFound if the team has none of that
    id, DatasetInUse naming the jobs that run on it."""
    store.delete_dataset(session, team_dataset(session, caller, dataset_id))
    session.commit()


def file_chunks(session_factory: SessionFactory, dataset_id: int) -> Iterator[bytes]:
    """The dataset's file as uploaded, chunk by chunk (for a streamed response that
    outlives the request's session), each chunk read in a short reading session of its
    own: a client that reads slowly, or not at all, holds no database connection
    while it is sent (with one session for the whole download, fifteen stalled
    downloads would take PostgreSQL's pool from every other request)."""
    with closing(session_factory(False)) as reader:
        seqs = store.chunk_seqs(reader, dataset_id, "file")
    for seq in seqs:
        with closing(session_factory(False)) as reader:
            chunk = store.read_chunk(reader, dataset_id, "file", seq)
        yield chunk


def download_name(row: Dataset) -> str:
    """The file name a download is saved under: the upload's, else dataset-ID.EXT."""
    ext = {"mat73": "mat"}.get(row.format, row.format)
    return row.filename or f"dataset-{row.id}.{ext}"


def dataset_view(row: Dataset, *, full: bool = True) -> dict:
    """A dataset as the API answers it; ``full`` adds every rollout's length and the
    per-channel statistics (the list leaves them out)."""
    out = {
        "id": row.id,
        "name": row.name,
        "description": row.description,
        "filename": row.filename,
        "format": row.format,
        "media_type": MEDIA_TYPES[row.format],
        "sha256": row.sha256,
        "arrays_sha256": row.arrays_sha256,
        "size_bytes": row.size_bytes,
        "n": row.n,
        "m": row.m,
        "rollouts": row.rollouts,
        "samples": row.samples,
        "T_min": row.t_min,
        "T_max": row.t_max,
        "sample_time": row.sample_time,
        "state_names": list(row.state_names),
        "input_names": list(row.input_names),
        "owner": row.user.email if row.user is not None else None,
        "created_at": row.created_at,
    }
    if full:
        out["lengths"] = list(row.lengths)
        out["stats"] = row.stats
        out["excitation"] = row.excitation
    return out
