"""Settings read from the environment (prefix ``SVROBS_``) by pydantic-settings.

Every process (API, worker, beat, CLI) reads the same settings; nothing else
configures the service.
"""

from __future__ import annotations

from functools import lru_cache

from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="SVROBS_", extra="ignore")

    DATABASE_URL: str = "sqlite:///./var/svrobs.db"
    BROKER_URL: str = "filesystem://"
    BROKER_DIR: str = "./var/broker"
    # How often the filesystem broker lists its folder when it has nothing to deliver.
    BROKER_POLL_SECONDS: float = 0.1
    # A worker whose consumer takes nothing while the broker's queue holds messages
    # and its pool has a free process reconnects after 3 checks this far apart
    # (worker.watchdog; Redis brokers only; 0 turns it off).
    WORKER_WATCHDOG_SECONDS: float = 20.0

    MAX_JOB_CELLS: int = 2_000_000
    MAX_BODY_BYTES: int = 1_048_576
    MAX_QUEUED_JOBS_PER_TEAM: int = 100
    RATE_LIMIT_PER_MINUTE: int = 600

    API_HOST: str = "127.0.0.1"
    API_PORT: int = 8000

    TASK_TIME_LIMIT: int = 3600
    # A unit whose lease ran out (worker died without the broker redelivering)
    # is re-published by the relay; the worker sets the lease when it starts.
    UNIT_LEASE_SECONDS: int = 3900
    # A unit published but never started is re-published after this long.
    PUBLISH_RETRY_SECONDS: int = 600
    # A unit that was started this many times without finishing is failed.
    MAX_UNIT_ATTEMPTS: int = 5

    # Seconds the API waits for the broker when publishing / in /readyz.
    BROKER_TIMEOUT: float = 2.0

    # Web UI sessions (service.web.session): the key that signs the session cookie
    # (unset: one is generated once and kept in ``secret_key`` beside the SQLite
    # database / broker folder, so restarts keep sessions; set it when several API
    # hosts serve the same users) and how long a sign-in lasts.
    SECRET_KEY: str | None = None
    SESSION_HOURS: float = 12.0


@lru_cache
def get_settings() -> Settings:
    return Settings()
