"""SQLAlchemy 2 ORM models. Tables are created only by Alembic (migrations/).

Result rows carry one SQL column per scalar record field
(docs/spec.md#record-fields; booleans as
Boolean, the rest Float/Integer) and the matrices as binary, keyed on (job,
system, sigma_w, N, estimator, gamma_key, rep) where ``gamma_key`` is gamma,
or -1 for ols (NULLs are never equal in a key).
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any, ClassVar

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    String,
    Table,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship
from sqlalchemy.types import TypeDecorator

from svrobs_core.records import BOOL_FIELDS, MATRIX_FIELDS, NUMERIC_FIELDS

JOB_STATUSES = ("queued", "running", "succeeded", "failed", "cancelled")
JOB_ACTIVE = ("queued", "running")
UNIT_STATUSES = ("pending", "running", "done", "failed", "cancelled")
OLS_GAMMA_KEY = -1.0
SHARE_LABEL_MAX = 200  # characters of a share link's label
TAG_MAX = 100  # characters of a job's tag as a request gives it (the column holds 200)


def utcnow() -> datetime:
    return datetime.now(UTC)


def as_utc(now: datetime | None = None) -> datetime:
    """``now`` (default: the current time) with a time zone; a naive time is taken as UTC."""
    now = now or utcnow()
    return now if now.tzinfo else now.replace(tzinfo=UTC)


class UTCDateTime(TypeDecorator):
    """Timezone-aware UTC datetimes on every dialect (SQLite stores them naive)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value, dialect):
        if value is None:
            return None
        if value.tzinfo is None:
            value = value.replace(tzinfo=UTC)
        value = value.astimezone(UTC)
        if dialect.name == "sqlite":
            return value.replace(tzinfo=None)
        return value

    def process_result_value(self, value, dialect):
        if value is None:
            return None
        if value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value.astimezone(UTC)


# the tables whose ids name a row outside its transaction (URLs, worker messages,
# schedules' templates, cookies): on SQLite an id without AUTOINCREMENT is reused
# after the newest row is deleted, so a deleted job's unit still computing could
# write into the next job; AUTOINCREMENT never hands an id out twice (PostgreSQL's
# sequences never do). Migration 0016 rebuilds the existing tables with it.
NEVER_REUSED: dict[str, Any] = {"sqlite_autoincrement": True}


class Base(DeclarativeBase):
    type_annotation_map = {datetime: UTCDateTime(), dict[str, Any]: JSON, list[Any]: JSON}
    __table__: ClassVar[Table]  # every model here maps one Table (declared: FromClause)


class Team(Base):
    __tablename__ = "teams"
    __table_args__ = NEVER_REUSED
    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    # retention of the team's scheduled jobs: cell rows dropped after this many days
    # (summaries and the stored report stay); None = keep everything (the default)
    retention_days: Mapped[int | None]


class User(Base):
    __tablename__ = "users"
    __table_args__ = NEVER_REUSED
    id: Mapped[int] = mapped_column(primary_key=True)
    team_id: Mapped[int] = mapped_column(ForeignKey("teams.id", ondelete="CASCADE"), index=True)
    email: Mapped[str] = mapped_column(String(320), unique=True)
    is_admin: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    team: Mapped[Team] = relationship()


class ApiKey(Base):
    __tablename__ = "api_keys"
    __table_args__ = NEVER_REUSED
    id: Mapped[int] = mapped_column(primary_key=True)
    prefix: Mapped[str] = mapped_column(String(16), unique=True, index=True)
    key_hash: Mapped[str] = mapped_column(String(64))  # sha256 hex of the whole key
    team_id: Mapped[int] = mapped_column(ForeignKey("teams.id", ondelete="CASCADE"), index=True)
    user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"))
    name: Mapped[str | None] = mapped_column(String(200))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[datetime | None]
    revoked_at: Mapped[datetime | None]
    last_used_at: Mapped[datetime | None]
    user: Mapped[User | None] = relationship()


class Job(Base):
    __tablename__ = "jobs"
    __table_args__ = (
        UniqueConstraint("team_id", "idempotency_key", name="uq_jobs_team_idempotency"),
        Index("ix_jobs_team_status", "team_id", "status"),
        Index("ix_jobs_team_created", "team_id", "created_at"),
        # beat's report thread polls for the newest finished jobs (reports.jobs_without_report)
        Index("ix_jobs_finished", "finished_at"),
        NEVER_REUSED,
    )
    id: Mapped[int] = mapped_column(primary_key=True)
    team_id: Mapped[int] = mapped_column(ForeignKey("teams.id", ondelete="CASCADE"))
    user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))
    schedule_id: Mapped[int | None] = mapped_column(
        ForeignKey("schedules.id", ondelete="SET NULL"), index=True
    )
    name: Mapped[str | None] = mapped_column(String(200))
    tags: Mapped[list[Any]] = mapped_column(default=list)
    spec: Mapped[dict[str, Any]]
    # what GET /jobs lists instead of the spec (jobs.spec_summary; None for a
    # job stored before the column existed)
    spec_summary: Mapped[dict[str, Any] | None]
    status: Mapped[str] = mapped_column(String(16), default="queued")
    progress_done: Mapped[int] = mapped_column(default=0)
    progress_total: Mapped[int] = mapped_column(default=0)
    n_cells: Mapped[int] = mapped_column(default=0)
    # cells of the units done so far (a cancelled job says how much of it ran)
    cells_done: Mapped[int] = mapped_column(default=0, server_default="0")
    provenance: Mapped[dict[str, Any]] = mapped_column(default=dict)
    idempotency_key: Mapped[str | None] = mapped_column(String(200))
    error: Mapped[str | None] = mapped_column(Text)
    timings: Mapped[dict[str, Any]] = mapped_column(default=dict)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]
    pruned_at: Mapped[datetime | None]  # when retention dropped its cell rows
    # the dataset of a job on measured data (its spec's "dataset"); a dataset that
    # jobs use cannot be deleted (service.db.datasets)
    dataset_id: Mapped[int | None] = mapped_column(ForeignKey("datasets.id"), index=True)

    user: Mapped[User | None] = relationship()
    tag_rows: Mapped[list[JobTag]] = relationship(
        cascade="all, delete-orphan", passive_deletes=True
    )


class JobTag(Base):
    """One row per (job, tag) so that ``GET /jobs?tag=`` is an indexed lookup."""

    __tablename__ = "job_tags"
    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True)
    tag: Mapped[str] = mapped_column(String(200), primary_key=True, index=True)  # <= TAG_MAX


class WorkUnit(Base):
    __tablename__ = "work_units"
    __table_args__ = (
        UniqueConstraint("job_id", "index", name="uq_work_units_job_index"),
        Index("ix_work_units_status_published", "status", "published_at"),
        NEVER_REUSED,
    )
    id: Mapped[int] = mapped_column(primary_key=True)
    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"))
    index: Mapped[int]
    payload: Mapped[dict[str, Any]]
    n_cells: Mapped[int] = mapped_column(default=0)
    status: Mapped[str] = mapped_column(String(16), default="pending")
    attempts: Mapped[int] = mapped_column(default=0)
    worker: Mapped[str | None] = mapped_column(String(200))
    published_at: Mapped[datetime | None]
    lease_expires_at: Mapped[datetime | None]
    error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]
    job: Mapped[Job] = relationship()


def _numeric_type(field: str):
    if field in BOOL_FIELDS:
        return Boolean
    if field in ("N", "N0", "rep"):
        return Integer
    return Float


# Columns of `results` that hold record fields, in the order of docs/spec.md#record-fields.
RESULT_SCALAR_FIELDS = tuple(NUMERIC_FIELDS)
RESULT_MATRIX_FIELDS = tuple(MATRIX_FIELDS)
RESULT_KEY = ("job_id", "system", "sigma_w", "N", "estimator", "gamma_key", "rep")
# The table's column order: 8-byte floats, then 4-byte integers, then booleans, then
# variable-length values, so that PostgreSQL pads no field to its alignment.
_FLOATS = ("sigma_w", "gamma_key") + tuple(
    f for f in NUMERIC_FIELDS if _numeric_type(f) is Float and f != "sigma_w"
)
_INTS = ("job_id", "N", "N0", "rep", "notes_id")
_BOOLS = tuple(BOOL_FIELDS)
_VARIABLE: tuple[str, ...] = ("system", "estimator", "bounds_method", "sls_status", "seed_key")
_VARIABLE += RESULT_MATRIX_FIELDS
RESULT_COLUMN_ORDER = _FLOATS + _INTS + _BOOLS + _VARIABLE


def _result_column(name: str):
    if name == "job_id":
        return mapped_column(Integer, primary_key=True)
    if name == "notes_id":
        return mapped_column(Integer, nullable=True)
    if name in ("system", "estimator"):
        return mapped_column(String(200 if name == "system" else 32), primary_key=True)
    if name == "gamma_key":
        return mapped_column(Float, primary_key=True)
    if name in ("sls_status", "bounds_method"):
        return mapped_column(String(64 if name == "sls_status" else 32), nullable=True)
    if name == "seed_key":
        return mapped_column(Text, nullable=True)
    if name in RESULT_MATRIX_FIELDS:
        return mapped_column(name, LargeBinary, nullable=True)
    key = name in ("sigma_w", "N", "rep")
    return mapped_column(name, _numeric_type(name), primary_key=key, nullable=not key)


class ResultNote(Base):
    """The distinct ``notes`` texts, stored once (results rows point here); ``digest``
    (sha256 of the text) is the unique key, as a text may be longer than an index entry."""

    __tablename__ = "result_notes"
    id: Mapped[int] = mapped_column(primary_key=True)
    digest: Mapped[str] = mapped_column(String(64), unique=True)
    text: Mapped[str] = mapped_column(Text)


class ResultConstant(Base):
    """A matrix field that is the same in every cell of a (job, system, sigma_w) (K),
    stored once; its rows hold zero bytes (``service.db.result_codec``)."""

    __tablename__ = "result_constants"
    job_id: Mapped[int] = mapped_column(primary_key=True)
    system: Mapped[str] = mapped_column(String(200), primary_key=True)
    sigma_w: Mapped[float] = mapped_column(Float, primary_key=True)
    field: Mapped[str] = mapped_column(String(32), primary_key=True)
    value: Mapped[bytes] = mapped_column(LargeBinary)


class ResultBlock(Base):
    """A unit's stored cells as report columns in one binary value
    (``service.db.result_blocks``): written with the unit's rows, read by a report
    build instead of the rows, dropped once the job's report is stored. No foreign
    key, as for ``results``."""

    __tablename__ = "result_blocks"
    job_id: Mapped[int] = mapped_column(primary_key=True)
    unit_id: Mapped[int] = mapped_column(primary_key=True)
    n_rows: Mapped[int]
    data: Mapped[bytes] = mapped_column(LargeBinary)


class Result(Base):
    """One cell (docs/spec.md#record-fields), keyed by its grid coordinates (the primary key;
    ``gamma_key`` is gamma, or -1 for ols). The compact format of migration 0005
    (``service.db.result_codec``): matrices as little-endian float64 bytes, their
    shapes from the job's spec; ``notes`` as an id into ``result_notes``;
    ``seed_key`` NULL when it is the one the spec gives (system and sigma_w
    indices, N, rep), else its JSON text. SQLite stores the table WITHOUT ROWID
    (clustered on the key: no second copy of it in an index).

    ``job_id`` and ``notes_id`` carry no foreign key: on PostgreSQL each costs a
    trigger check per stored row (11 us, half the COPY of a unit) and the job's
    check takes KEY SHARE locks on the job row that the unit completion of another
    worker holds FOR UPDATE. Rows are written only by ``complete_unit`` for an
    existing job; ``result_notes`` is never deleted from."""

    __tablename__ = "results"
    __table_args__ = {"sqlite_with_rowid": False}

    # One column per numeric field and per matrix field, named exactly as in
    # docs/spec.md#record-fields
    # (a class body's namespace is a plain dict, so the loop can add them).
    _ns = locals()
    for _f in RESULT_COLUMN_ORDER:
        _ns[_f] = _result_column(_f)
    del _ns, _f
    if TYPE_CHECKING:  # the columns the code names, as the type checker sees them
        job_id: Mapped[int]


class Summary(Base):
    __tablename__ = "summaries"
    __table_args__ = (
        UniqueConstraint(
            "job_id", "system", "sigma_w", "N", "estimator", "gamma_key", name="uq_summaries_group"
        ),
    )
    id: Mapped[int] = mapped_column(primary_key=True)
    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    system: Mapped[str] = mapped_column(String(200))
    sigma_w: Mapped[float] = mapped_column(Float)
    N: Mapped[int] = mapped_column("N", Integer)
    estimator: Mapped[str] = mapped_column(String(32))
    gamma: Mapped[float | None] = mapped_column(Float)
    gamma_key: Mapped[float] = mapped_column(Float)
    count: Mapped[int]
    stats: Mapped[dict[str, Any]]


class JobReport(Base):
    """A finished job's HTML report, built once (finished jobs do not change) and
    again when the page's layout changed (``layout``: the
    ``svrobs_lab.report_html.REPORT_LAYOUT`` it was built with; 0 for a report stored
    before the column existed), unless the job's rows were pruned."""

    __tablename__ = "job_reports"
    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True)
    html: Mapped[str] = mapped_column(Text)
    n_records: Mapped[int]
    built_at: Mapped[datetime] = mapped_column(default=utcnow)
    layout: Mapped[int] = mapped_column(default=0, server_default="0")


class JobValidation(Base):
    """A dataset job's validation on its held-out rollouts and the excitation check
    of its training data (``svrobs_core.measured.validation_summary``), computed once."""

    __tablename__ = "job_validations"
    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True)
    summary: Mapped[dict[str, Any]]
    built_at: Mapped[datetime] = mapped_column(default=utcnow)


class Schedule(Base):
    __tablename__ = "schedules"
    __table_args__ = (
        UniqueConstraint("team_id", "name", name="uq_schedules_team_name"),
        NEVER_REUSED,
    )
    id: Mapped[int] = mapped_column(primary_key=True)
    team_id: Mapped[int] = mapped_column(ForeignKey("teams.id", ondelete="CASCADE"), index=True)
    user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))
    name: Mapped[str] = mapped_column(String(200))
    cron: Mapped[str] = mapped_column(String(200))
    timezone: Mapped[str] = mapped_column(String(64), default="UTC")
    spec_template: Mapped[dict[str, Any]]
    tags: Mapped[list[Any]] = mapped_column(default=list)
    enabled: Mapped[bool] = mapped_column(Boolean, default=True)
    # "fixed": every run uses the template's seed; "due-time": derived from the due time
    seed_policy: Mapped[str] = mapped_column(String(16), default="fixed", server_default="fixed")
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow, onupdate=utcnow)


class ScheduleRun(Base):
    __tablename__ = "schedule_runs"
    __table_args__ = (
        UniqueConstraint("schedule_id", "due_at", name="uq_schedule_runs_due"),
        NEVER_REUSED,
    )
    id: Mapped[int] = mapped_column(primary_key=True)
    schedule_id: Mapped[int] = mapped_column(ForeignKey("schedules.id", ondelete="CASCADE"))
    due_at: Mapped[datetime]
    job_id: Mapped[int | None] = mapped_column(ForeignKey("jobs.id", ondelete="SET NULL"))
    error: Mapped[str | None] = mapped_column(Text)
    # why no job was made for this due time although the spec is valid (team's cap...)
    skipped_reason: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class ShareLink(Base):
    """A read-only link to one job's report and charts (service.db.shares): the token
    is stored as its SHA-256 only; it expires, and can be revoked."""

    __tablename__ = "share_links"
    __table_args__ = NEVER_REUSED
    id: Mapped[int] = mapped_column(primary_key=True)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    team_id: Mapped[int] = mapped_column(ForeignKey("teams.id", ondelete="CASCADE"))
    user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[datetime]
    revoked_at: Mapped[datetime | None]
    label: Mapped[str | None] = mapped_column(String(SHARE_LABEL_MAX))  # what it is for


class Dataset(Base):
    """An uploaded file of measured rollouts (docs/datasets.md#the-data-model), team-scoped
    like jobs: its shapes, channel names and statistics here; the original bytes and
    the arrays (float64) in ``dataset_chunks``."""

    __tablename__ = "datasets"
    __table_args__ = (Index("ix_datasets_team_created", "team_id", "created_at"), NEVER_REUSED)
    id: Mapped[int] = mapped_column(primary_key=True)
    team_id: Mapped[int] = mapped_column(ForeignKey("teams.id", ondelete="CASCADE"))
    user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))
    name: Mapped[str] = mapped_column(String(200))
    description: Mapped[str | None] = mapped_column(Text)
    filename: Mapped[str | None] = mapped_column(String(255))
    format: Mapped[str] = mapped_column(String(16))  # csv, npz, mat, mat73, json
    sha256: Mapped[str] = mapped_column(String(64))  # of the original bytes
    arrays_sha256: Mapped[str] = mapped_column(String(64))  # of the stored float64 arrays
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    n: Mapped[int]
    m: Mapped[int]
    rollouts: Mapped[int]
    samples: Mapped[int] = mapped_column(BigInteger)  # sum of the rollouts' steps T_i
    t_min: Mapped[int]  # the shortest and longest T_i (a listing reads no lengths)
    t_max: Mapped[int]
    lengths: Mapped[list[Any]]  # T_i of each rollout (it has T_i + 1 states)
    sample_time: Mapped[float | None] = mapped_column(Float)
    state_names: Mapped[list[Any]]
    input_names: Mapped[list[Any]]
    stats: Mapped[dict[str, Any]]  # {"states"|"inputs": {name: {mean, std, min, max, count}}}
    # the excitation check of all its rollouts, made at upload (None: too large to make
    # then, or uploaded before it was stored)
    excitation: Mapped[dict[str, Any] | None]
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    user: Mapped[User | None] = relationship()


class DatasetChunk(Base):
    """A dataset's bytes in pieces of at most 1 MiB: ``part`` "file" (the upload as
    sent) or "arrays" (every X_i, then every U_i, little-endian float64, row-major),
    in ``seq`` order."""

    __tablename__ = "dataset_chunks"
    dataset_id: Mapped[int] = mapped_column(
        ForeignKey("datasets.id", ondelete="CASCADE"), primary_key=True
    )
    part: Mapped[str] = mapped_column(String(8), primary_key=True)
    seq: Mapped[int] = mapped_column(primary_key=True)
    data: Mapped[bytes] = mapped_column(LargeBinary)


class SignIn(Base):
    """A web sign-in (service.db.sign_ins): the SHA-256 of the session cookie's id and
    the key signed in with; a cookie is a session only while its row is here (signing
    out deletes it)."""

    __tablename__ = "sessions"
    __table_args__ = NEVER_REUSED
    id: Mapped[int] = mapped_column(primary_key=True)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    key_id: Mapped[int] = mapped_column(ForeignKey("api_keys.id", ondelete="CASCADE"), index=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[datetime]
