"""Settings read from the environment (prefix ``SVROBS_``) by pydantic-settings.

Every process (API, worker, beat, CLI) reads the same settings; nothing else
reads the environment for them. The URLs are checked when the settings are
made: a malformed one fails at start-up with an error naming its variable.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from service.pool_size import default_pool_processes

# The Celery transports the service is run with (filesystem: the embedded default).
BROKER_SCHEMES = ("filesystem", "redis", "rediss", "memory", "amqp")


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="SVROBS_", extra="ignore")

    DATABASE_URL: str = "sqlite:///./var/svrobs.db"
    BROKER_URL: str = "filesystem://"
    # The state folder (SQLite file, broker folders, beat's schedule file by default).
    VAR_DIR: str = "./var"
    BROKER_DIR: str = "./var/broker"
    # How often the filesystem broker lists its folder when it has nothing to deliver.
    BROKER_POLL_SECONDS: float = 0.1
    # A worker whose consumer takes nothing while the broker's queue holds messages
    # and its pool has a free process reconnects after 3 checks this far apart
    # (worker.watchdog; Redis brokers only; 0 turns it off).
    WORKER_WATCHDOG_SECONDS: float = 20.0
    # Beat's tick (due schedules, then the relay) runs this often.
    TICK_SECONDS: float = Field(default=60.0, gt=0)
    # Beat looks for finished jobs without a stored report this often (and at least
    # every tick), and builds theirs, so a report is usually stored before it is asked.
    REPORT_POLL_SECONDS: float = Field(default=5.0, gt=0)

    MAX_JOB_CELLS: int = 2_000_000
    # Admission (svrobs_core.admission, docs/deploy.md#admission): a job whose records
    # would take more than this many MB in the store (cells x their matrix entries,
    # from the grid's axis lengths) gets 422 before anything is planned.
    MAX_JOB_STORED_MB: float = 10_240.0
    # Admission by work (svrobs_core.workload): a job whose estimated CPU time is over
    # this, or one of whose units would need more memory than MAX_UNIT_MEMORY_MB or
    # more CPU seconds than MAX_UNIT_CPU_SECONDS even split down to one repetition,
    # gets 422; units are planned to stay under both caps.
    MAX_JOB_CPU_SECONDS: float = 3_600.0
    MAX_UNIT_MEMORY_MB: int = 2048
    MAX_UNIT_CPU_SECONDS: float = 600.0
    # A JSON page of results holds at most this many matrix entries (A_hat, B_hat,
    # radii, gains): a longer page is shortened and says where the next one starts.
    MAX_PAGE_MATRIX_ENTRIES: int = 1_000_000
    # The pool processes that run units, all workers together (`svrobs serve` sets it
    # to its workers x --concurrency; default what it starts: one worker with one
    # process per CPU plus one, at most 5). The fair share follows it.
    WORKER_POOL_PROCESSES: int = Field(default_factory=default_pool_processes, ge=1)
    # Fair share: at most this many units of one team are published and not finished
    # at once; the rest are published as they finish, round-robin over teams (0: no
    # cap). Unset: the pool's size, one less while another team has units queued or
    # running, so that another team's unit always finds a free process (fair_share).
    MAX_UNITS_IN_FLIGHT_PER_TEAM: int | None = Field(default=None, ge=0)
    MAX_SCHEDULES_PER_TEAM: int = 20
    # A schedule's cron must not fire more often than this (seconds between runs).
    MIN_SCHEDULE_INTERVAL_SECONDS: int = 300
    MAX_BODY_BYTES: int = 1_048_576
    # A dataset upload (POST /datasets, streamed to a temporary file) may be at most
    # this many MB (2^20 bytes): 413 beyond (docs/datasets.md#limits).
    MAX_DATASET_MB: int = 256
    # A team's stored datasets (docs/datasets.md#limits): at most this many, holding at
    # most this many MB together (each upload's bytes plus its float64 arrays); an
    # upload beyond either is refused (422 naming the setting) before anything is
    # stored. 0: no cap.
    MAX_DATASETS_PER_TEAM: int = Field(default=200, ge=0)
    MAX_TEAM_DATASETS_MB: int = Field(default=8192, ge=0)
    # A job's live share links (not revoked, not expired: svrobs_lab.shares): at most
    # this many; making one more is refused (422 naming the setting) until one is
    # revoked or expires. Counted under the team's quota lock. 0: no cap.
    MAX_SHARES_PER_JOB: int = Field(default=100, ge=0)
    # Uploads read and parsed at once in each API process: at most this many of one
    # team and this many in all (a file can take several times its size in memory
    # while it is parsed); beyond, 429 with Retry-After.
    UPLOADS_PER_TEAM: int = Field(default=2, ge=1)
    UPLOADS_AT_ONCE: int = Field(default=4, ge=1)
    # Results streamed at once (CSV, JSON lines) in each API process: a stream reads
    # its rows through one database connection, held until the client has read the
    # last of them; at most this many of one team and this many in all (below the 15
    # connections of a process's pool of reads); beyond, 429 with Retry-After.
    STREAMS_PER_TEAM: int = Field(default=2, ge=1)
    STREAMS_AT_ONCE: int = Field(default=8, ge=1)
    # A connection whose request headers are not complete this long after it opened,
    # or after its last response, is closed (service.http.request_deadlines).
    HEADER_TIMEOUT_SECONDS: float = Field(default=10.0, gt=0)
    # A request's body must be whole this long after its headers, plus one second
    # per BODY_MIN_BYTES_PER_SECOND bytes of it received; else its connection is
    # closed (service.http.request_deadlines). Time the server spends not reading
    # does not count.
    BODY_TIMEOUT_SECONDS: float = Field(default=20.0, gt=0)
    BODY_MIN_BYTES_PER_SECOND: float = Field(default=500.0, gt=0)
    MAX_QUEUED_JOBS_PER_TEAM: int = 100
    RATE_LIMIT_PER_MINUTE: int = 600
    # Failed authentications (a bad sign-in, a bad bearer key) per client address per
    # minute, in each API process: beyond, 429 with Retry-After (0: no limit).
    AUTH_FAILURES_PER_MINUTE: int = 10
    # A report's figures are drawn as PNG by this many helper processes of each
    # process that builds reports (API, beat), started at its first report, while the
    # build goes on (svrobs_lab.figure_pool; 0: drawn in the building process).
    REPORT_RENDER_PROCESSES: int = Field(default=2, ge=0)
    # Report builds (svrobs_lab.report_builds), in each API process: at most this many
    # builds of one team at once (a report, or a dataset job's validation computed on
    # request), and this many of its requests waiting for a build of the same job;
    # beyond, 429 with Retry-After.
    REPORT_BUILDS_PER_TEAM: int = 2
    REPORT_WAITERS_PER_TEAM: int = 8

    API_HOST: str = "127.0.0.1"
    API_PORT: int = 8000

    TASK_TIME_LIMIT: int = 3600
    # A unit whose lease ran out (worker died without the broker redelivering)
    # is re-published by the relay; the worker sets the lease when it starts and
    # renews it every third of it while the unit computes (docs/deploy.md#scaling).
    UNIT_LEASE_SECONDS: int = Field(default=300, ge=3)
    # A unit published but never started is re-published after this long.
    PUBLISH_RETRY_SECONDS: int = 600
    # A unit that was started this many times without finishing is failed (0: never).
    MAX_UNIT_ATTEMPTS: int = 5

    # How often a running unit checks whether it was cancelled (its job cancelled or
    # failed); a cancelled unit stops within about this long.
    CANCEL_CHECK_SECONDS: float = 1.0

    # Seconds the API waits for the broker when publishing / in /readyz.
    BROKER_TIMEOUT: float = 2.0
    # The folder of this host's worker pid files (`svrobs serve` sets it for its API):
    # when set, /readyz is 503 while none of those workers is alive (service.worker_pids).
    WORKER_PID_DIR: str | None = None

    # Web UI sessions (svrobs_lab.sessions): the key that signs the session cookie
    # (unset: one is generated once and kept in VAR_DIR/secret_key, so restarts keep
    # sessions; set it when API processes on several hosts serve the same users) and
    # how long a sign-in lasts.
    SECRET_KEY: str | None = None
    SESSION_HOURS: float = 12.0
    # Whether the session cookie is Secure (sent over https only). Unset: when the
    # request came over https as uvicorn sees it, which behind a TLS proxy is only so
    # when uvicorn trusts the proxy's X-Forwarded-Proto (--forwarded-allow-ips); set it
    # to true when every user reaches the dashboard over https.
    SESSION_COOKIE_SECURE: bool | None = None

    # The level of every svrobs process's log (service.logging_config).
    LOG_LEVEL: Literal["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"] = "INFO"
    # The commit stored in job provenance; unset: ``git rev-parse HEAD`` of the checkout.
    GIT_COMMIT: str | None = None

    # TEST-ONLY fault injection, off by default (tests/faults): running this unit
    # kills its worker process; the consumer stops consuming after its first message.
    TEST_CRASH_UNIT: int | None = None
    TEST_STALL_CONSUMER: bool = False

    def fair_share(self) -> tuple[int, int]:
        """``(alone, shared)``: the cap on a team's units in flight while no other team
        has units queued or running, and while one has (0: no cap); see
        docs/architecture.md#one-job."""
        k = self.MAX_UNITS_IN_FLIGHT_PER_TEAM
        if k is not None:
            return k, k
        pool = self.WORKER_POOL_PROCESSES
        return pool, max(1, pool - 1)

    @field_validator("LOG_LEVEL", mode="before")
    @classmethod
    def _upper_level(cls, value):
        return value.strip().upper() if isinstance(value, str) else value

    @field_validator("DATABASE_URL")
    @classmethod
    def _database_url(cls, value: str) -> str:
        # imported here: the CLI's REST commands import this module and never need it
        from sqlalchemy.engine import make_url
        from sqlalchemy.exc import ArgumentError

        try:
            make_url(value)
        except (ArgumentError, ValueError):  # ValueError: a port that is not a number
            raise ValueError(
                f"SVROBS_DATABASE_URL is not a database URL: {value!r} "
                "(e.g. sqlite:///./var/svrobs.db or postgresql+psycopg://user@host/db)"
            ) from None
        return value

    @field_validator("BROKER_URL")
    @classmethod
    def _broker_url(cls, value: str) -> str:
        scheme, sep, _rest = value.partition("://")
        if not sep or scheme not in BROKER_SCHEMES:
            raise ValueError(
                f"SVROBS_BROKER_URL is not a broker URL: {value!r} "
                f"(the scheme must be one of {', '.join(BROKER_SCHEMES)}, e.g. redis://host:6379/0)"
            )
        return value


@lru_cache
def get_settings() -> Settings:
    return Settings()
