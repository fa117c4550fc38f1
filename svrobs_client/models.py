"""Result objects of the client: a job, its progress, a page of jobs, a schedule and its
runs, a share link, a dataset. Built from the API's JSON; ``raw`` keeps that JSON as received."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, fields
from datetime import datetime
from pathlib import Path
from typing import Any, Self, TypeVar

from .errors import SvrobsError

_T = TypeVar("_T")

TERMINAL = ("succeeded", "failed", "cancelled")


def ident(obj: object) -> int:
    """The id of a Job, Schedule, Share or Dataset, or an id given as an int or a string
    of digits; a TypeError or ValueError (saying so) for anything else."""
    value = getattr(obj, "id", obj)
    if isinstance(value, bool) or not isinstance(value, (int, str)):
        raise TypeError(f"expected an id or an object with one, got {type(obj).__name__}")
    if isinstance(value, str) and not (value.isascii() and value.isdigit()):
        raise ValueError(f"{value!r} is not an id: ids are whole numbers (digits 0-9)")
    return int(value)


def _time(value: str | None) -> datetime | None:
    if not value:
        return None
    return datetime.fromisoformat(value.replace("Z", "+00:00"))


def _check_shape(cls: type, data: object) -> None:
    """A SvrobsError unless ``data`` is a JSON object (with an integer ``id`` where
    ``cls`` has one): what an answer of another server would not be."""
    names = {f.name for f in fields(cls)}
    if not isinstance(data, dict) or ("id" in names and not isinstance(data.get("id"), int)):
        kind = cls.__name__.lower()
        raise SvrobsError(
            f"the answer is not a {kind} of the svrobs API (is SVROBS_URL its address?)"
        )


def answer(
    body: object, what: str, *, rows: str | None = None, counts: tuple[str, ...] = ()
) -> Any:
    """``body`` if it has the shape of the API's answer ``what``: a JSON list when
    ``rows`` is None, else an object whose ``rows`` is a list and whose ``counts`` are
    integers; a SvrobsError saying so otherwise (another server answering JSON)."""
    if rows is None:
        ok = isinstance(body, list)
    else:
        ok = (
            isinstance(body, dict)
            and isinstance(body.get(rows), list)
            and all(isinstance(body.get(k), int) for k in counts)
        )
    if not ok:
        raise SvrobsError(
            f"the answer is not {what} of the svrobs API (is SVROBS_URL its address?)"
        )
    return body


def _build(cls: type[_T], data: dict[str, Any], **given: Any) -> _T:
    """``cls`` from the API's JSON: each field from the key of its name (``*_at`` parsed
    as a datetime, a missing list or dict empty), unless ``given``; ``raw`` = ``data``."""
    dataclass_: Any = cls  # every caller is a dataclass
    _check_shape(cls, data)
    kw: dict[str, Any] = {}
    for f in fields(dataclass_):
        if f.name == "raw":
            continue
        if f.name in given:
            kw[f.name] = given[f.name]
        elif f.name.endswith("_at"):
            kw[f.name] = _time(data.get(f.name))
        elif f.type.startswith(("list", "dict")):
            value = data.get(f.name) or ()
            kw[f.name] = list(value) if f.type.startswith("list") else dict(value)
        else:
            kw[f.name] = data.get(f.name)
    built: _T = dataclass_(**kw, raw=data)
    return built


class _FromJSON:
    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Self:
        """Built from the API's JSON body."""
        return _build(cls, data)


@dataclass(frozen=True)
class Progress:
    """Work units done out of total (``fraction`` as the API reports it)."""

    done: int
    total: int
    fraction: float


@dataclass(frozen=True)
class Job(_FromJSON):
    """One job as ``GET /api/v1/jobs/{id}`` returns it."""

    id: int
    name: str | None
    tags: list[str]
    status: str
    progress: Progress
    n_cells: int
    owner: str | None
    spec: dict[str, Any] = field(repr=False)
    provenance: dict[str, Any] = field(repr=False)
    error: str | None
    timings: dict[str, Any] = field(repr=False)
    created_at: datetime | None
    started_at: datetime | None
    finished_at: datetime | None
    schedule_id: int | None = None
    idempotency_key: str | None = None
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Job:
        _check_shape(cls, data)
        p = data.get("progress") or {}
        if not isinstance(p, dict):
            p = {}
        progress = Progress(
            done=int(p.get("done", 0)),
            total=int(p.get("total", 0)),
            fraction=float(p.get("fraction", 0.0)),
        )
        return _build(cls, data, progress=progress, n_cells=int(data.get("n_cells") or 0))

    @property
    def finished(self) -> bool:
        """True once the job is succeeded, failed or cancelled."""
        return self.status in TERMINAL


@dataclass(frozen=True)
class JobPage:
    """A page of ``GET /api/v1/jobs``: iterate it for the jobs; ``total`` counts every
    job matching the filters."""

    items: list[Job]
    total: int
    limit: int
    offset: int

    def __iter__(self) -> Iterator[Job]:
        return iter(self.items)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> Job:
        return self.items[i]


@dataclass(frozen=True)
class Schedule(_FromJSON):
    """A cron schedule: a spec template turned into a job at every due time."""

    id: int
    name: str
    cron: str
    timezone: str
    spec_template: dict[str, Any] = field(repr=False)
    tags: list[str]
    enabled: bool
    next_run_at: datetime | None
    created_at: datetime | None
    updated_at: datetime | None
    seed_policy: str = "fixed"
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)


@dataclass(frozen=True)
class ScheduleRun(_FromJSON):
    """One due time of a schedule already turned into a job (``job_id``) or an error."""

    id: int
    due_at: datetime | None
    job_id: int | None
    error: str | None
    created_at: datetime | None
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)


@dataclass(frozen=True)
class Share(_FromJSON):
    """A read-only link to one job's report and charts, opened without a key until it
    expires or is revoked. ``label`` says what it is for (None: no label); ``url`` is
    only known in the answer that created it."""

    id: int
    job_id: int
    label: str | None
    created_at: datetime | None
    expires_at: datetime | None
    revoked_at: datetime | None
    live: bool
    url: str | None = None
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def token(self) -> str | None:
        """The link's secret (the last part of ``url``), or None when not known."""
        return self.url.rstrip("/").rsplit("/", 1)[-1] if self.url else None


@dataclass(frozen=True)
class Report:
    """What :meth:`Client.report` wrote: the HTML page and the figures found in it."""

    html: Path
    figures: list[Path]


@dataclass(frozen=True)
class Dataset(_FromJSON):
    """An uploaded dataset of measured rollouts (``GET /api/v1/datasets/{id}``):
    shapes, channel names, sha256 of the upload and of its arrays; ``lengths`` and
    ``stats`` (per channel mean, std, min, max) are empty in a listed one."""

    id: int
    name: str
    format: str
    n: int
    m: int
    rollouts: int
    samples: int
    sha256: str
    arrays_sha256: str = field(repr=False)
    size_bytes: int = field(repr=False)
    sample_time: float | None = None
    state_names: list[str] = field(default_factory=list)
    input_names: list[str] = field(default_factory=list)
    lengths: list[int] = field(default_factory=list, repr=False)
    stats: dict[str, Any] = field(default_factory=dict, repr=False)
    description: str | None = field(default=None, repr=False)
    filename: str | None = None
    owner: str | None = field(default=None, repr=False)
    created_at: datetime | None = None
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)


@dataclass(frozen=True)
class DatasetPage:
    """A page of ``GET /api/v1/datasets``; ``total`` counts the team's datasets."""

    items: list[Dataset]
    total: int
    limit: int
    offset: int

    def __iter__(self) -> Iterator[Dataset]:
        return iter(self.items)

    def __len__(self) -> int:
        return len(self.items)
