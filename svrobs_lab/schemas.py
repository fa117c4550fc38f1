"""Request and response bodies. Request bodies forbid unknown fields (HTTP 422):
the team and owner always come from the API key, never from a body."""

from __future__ import annotations

from datetime import datetime
from typing import TYPE_CHECKING, Annotated, Any, Literal, Optional

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    StringConstraints,
    WithJsonSchema,
    create_model,
    model_validator,
)
from pydantic_core import InitErrorDetails, PydanticCustomError, ValidationError

from service.db.models import TAG_MAX
from svrobs_core.spec import DATASET_KEYS, SPEC_KEYS
from svrobs_core.text import NOT_PRINTABLE, printable

from .spec_schema import spec_properties

SPEC_FIELDS = SPEC_KEYS | DATASET_KEYS  # a simulated job's fields and a dataset job's

# Loose types: svrobs_core.parse_spec does the real validation with field-named errors.
# A spec has systems and sigma_w (a list), or a dataset (and sigma_w a number or
# "estimate": docs/measured.md#spec). The schema shown for each field (OpenAPI) is
# the declared table's (spec_schema).
_SPEC_HINTS: dict[str, Any] = {
    "systems": (Optional[list[Any]], None),
    "sigma_w": (Any, None),
    "dataset": (Optional[int], None),
    "N": (list[Any] | dict[str, Any], ...),
    "gamma": (Optional[list[Any]], None),
    "estimators": (Optional[list[Any]], None),
    "stages": (Optional[list[Any]], None),
    "sls": (Optional[dict[str, Any]], None),
}


def _text_error(s: str) -> str | None:
    if "\x00" in s:
        return "must not contain NUL (\\u0000) characters"
    try:
        s.encode("utf-8")
    except UnicodeEncodeError:
        return "must be valid Unicode (no lone surrogates)"
    return None


def bad_text(value: Any) -> tuple[tuple, str] | None:
    """``(location, message)`` of a string (value or key) in ``value`` that no database
    can store and no JSON response can carry: a NUL character (PostgreSQL text rejects
    it) or a lone surrogate (not UTF-8 encodable). None if every string is clean.
    Iterative, so a deeply nested body cannot exhaust the stack."""
    stack: list[tuple[tuple, Any]] = [((), value)]
    while stack:
        loc, v = stack.pop()
        if isinstance(v, str):
            err = _text_error(v)
            if err is not None:
                return loc, err
        elif isinstance(v, dict):
            for k, item in reversed(list(v.items())):
                err = _text_error(k) if isinstance(k, str) else None
                if err is not None:
                    return loc, f"keys {err}"
                stack.append(((*loc, k), item))
        elif isinstance(v, (list, tuple)):
            stack.extend(((*loc, i), item) for i, item in reversed(list(enumerate(v))))
    return None


class _Strict(BaseModel):
    """A request body: unknown fields forbidden, no coercion (``"yes"`` is not a bool,
    ``3.0`` not an int), strings stripped before their length is checked."""

    model_config = ConfigDict(extra="forbid", strict=True, str_strip_whitespace=True)

    @model_validator(mode="before")
    @classmethod
    def _clean_text(cls, data: Any) -> Any:
        found = bad_text(data)
        if found is not None:
            loc, message = found
            raise ValidationError.from_exception_data(
                cls.__name__,
                [
                    InitErrorDetails(
                        type=PydanticCustomError("bad_text", message), loc=loc, input=None
                    )
                ],
            )
        return data


def _no_default(schema: dict[str, Any]) -> None:
    schema.pop("default", None)  # a key without a default (systems, sigma_w, dataset)


def _spec_fields() -> dict[str, Any]:
    schemas = spec_properties()
    out = {}
    for key in sorted(SPEC_FIELDS):
        hint, default = _SPEC_HINTS.get(key, (Any, None))
        schema = schemas[key]
        # absent stays absent (None) for the parser; the schema shows the spec's default
        extra = {"default": schema["default"]} if "default" in schema else _no_default
        out[key] = (
            Annotated[hint, WithJsonSchema(schema)],
            Field(default, json_schema_extra=extra),
        )
    return out


def _printable(text: str) -> str:
    if not printable(text):
        raise ValueError(NOT_PRINTABLE)
    return text


TagStr = Annotated[
    str,
    StringConstraints(strip_whitespace=True, min_length=1, max_length=TAG_MAX),
    AfterValidator(_printable),
]
# a job's or a schedule's name: shown in terminals, pages and file names
NameStr = Annotated[
    str, StringConstraints(min_length=1, max_length=200), AfterValidator(_printable)
]
Tag: Any = Field(default_factory=list, max_length=50)

_JobSubmit = create_model(
    "JobSubmit",
    __base__=_Strict,
    __doc__="An experiment spec (docs/spec.md#spec-fields: systems and sigma_w; or a dataset,"
    " docs/measured.md#spec) plus an optional name and tags.",
    name=(Optional[NameStr], None),
    tags=(list[TagStr], Tag),
    **_spec_fields(),
)
if TYPE_CHECKING:

    class JobSubmit(_Strict):
        """The model built above, as a class the type checker can name (its fields are
        made from the spec's table at import)."""

else:
    JobSubmit = _JobSubmit

SPEC_FIELD_NAMES = tuple(sorted(SPEC_FIELDS))


class Progress(BaseModel):
    done: int
    total: int
    fraction: float


class _JobBase(BaseModel):
    id: int
    name: str | None
    tags: list[str]
    status: str
    progress: Progress
    n_cells: int
    cells_done: int
    owner: str | None
    schedule_id: int | None
    idempotency_key: str | None
    provenance: dict[str, Any]
    error: str | None
    timings: dict[str, Any]
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    pruned_at: datetime | None  # retention dropped its cell rows (results: 410)


class JobOut(_JobBase):
    spec: dict[str, Any]


class JobItem(_JobBase):
    """A listed job: the spec's summary (system names, grid sizes, stages, cells);
    the full spec is at ``GET /jobs/{id}``."""

    spec_summary: dict[str, Any]


class Page(BaseModel):
    total: int
    limit: int
    offset: int


class JobPage(Page):
    items: list[JobItem]


class ResultPage(Page):
    items: list[dict[str, Any]]
    # where the next page starts (null after the last); a page holds at most
    # SVROBS_MAX_PAGE_MATRIX_ENTRIES matrix entries, so its limit may be lower
    next_offset: int | None = None


class SummaryOut(Page):
    job_id: int
    partial: bool
    groups: list[dict[str, Any]]


class CompareOut(Page):
    metric: str
    by: list[str]
    jobs: list[int]
    rows: list[dict[str, Any]]


SeedPolicy = Annotated[
    Literal["fixed", "due-time"],
    Field(
        description="fixed: every run uses the template's seed; due-time: (template seed + "
        "the due time in Unix seconds) mod 2^31, so each run adds fresh repetitions"
    ),
]


class ScheduleCreate(_Strict):
    name: NameStr
    cron: str = Field(min_length=1, max_length=200)
    timezone: str = Field(default="UTC", min_length=1, max_length=64)
    spec_template: dict[str, Any]
    tags: list[TagStr] = Tag
    enabled: bool = True
    seed_policy: SeedPolicy = "fixed"


class ScheduleUpdate(_Strict):
    name: NameStr | None = None
    cron: str | None = Field(default=None, min_length=1, max_length=200)
    timezone: str | None = Field(default=None, min_length=1, max_length=64)
    spec_template: dict[str, Any] | None = None
    tags: list[TagStr] | None = Field(default=None, max_length=50)
    enabled: bool | None = None
    seed_policy: SeedPolicy | None = None


class ScheduleOut(BaseModel):
    id: int
    name: str
    cron: str
    timezone: str
    spec_template: dict[str, Any]
    tags: list[str]
    enabled: bool
    seed_policy: SeedPolicy
    next_run_at: datetime | None
    created_at: datetime
    updated_at: datetime


class ScheduleRunOut(BaseModel):
    id: int
    due_at: datetime
    job_id: int | None
    error: str | None
    skipped_reason: str | None
    created_at: datetime


class ErrorOut(BaseModel):
    detail: Any
    field: str | None = None
