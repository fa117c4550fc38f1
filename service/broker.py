"""The single place Celery is configured, and publishing of work units.

The worker does ``celery_app = make_celery(get_settings())`` and registers
its task under :data:`RUN_UNIT_TASK`; the API and the relay publish with
:func:`publish_units` after the job is committed (the one relay is
``worker.tick.relay``).
"""

from __future__ import annotations

import logging
import os
import ssl
from collections.abc import Callable, Iterable
from typing import cast

from celery import Celery

from service.config import Settings
from service.file_broker import TRANSPORT as FILE_TRANSPORT
from service.redis_broker import TRANSPORT as REDIS_TRANSPORT

log = logging.getLogger(__name__)

RUN_UNIT_TASK = "svrobs.run_unit"
# Publishing from a request must not hang while the broker is down: one quick
# retry, then the relay re-publishes from the DB later.
PUBLISH_RETRY_POLICY = {
    "max_retries": 1,
    "interval_start": 0,
    "interval_step": 0.2,
    "interval_max": 0.2,
}


def is_filesystem(url: str) -> bool:
    return url.startswith("filesystem:")


def filesystem_folders(settings: Settings) -> dict[str, str]:
    base = os.path.abspath(settings.BROKER_DIR)
    return {
        "data_folder_in": os.path.join(base, "queue"),
        "data_folder_out": os.path.join(base, "queue"),
        "processed_folder": os.path.join(base, "processed"),
        "control_folder": os.path.join(base, "control"),
        # messages that cannot be decoded are moved here (service.file_broker)
        "bad_folder": os.path.join(base, "bad"),
    }


def _ensure_folders(settings: Settings) -> dict[str, str]:
    folders = filesystem_folders(settings)
    for path in folders.values():
        os.makedirs(path, exist_ok=True)
    return folders


def make_celery(settings: Settings, name: str = "svrobs") -> Celery:
    """A Celery app for ``settings.BROKER_URL`` (JSON only, late acks, prefetch 1)."""
    app = Celery(name, broker=settings.BROKER_URL)
    limit = int(settings.TASK_TIME_LIMIT)
    conf: dict = dict(
        task_serializer="json",
        result_serializer="json",
        accept_content=["json"],
        event_serializer="json",
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        task_time_limit=limit,
        task_soft_time_limit=max(1, limit - min(60, limit // 10)),
        task_ignore_result=True,
        result_backend=None,
        task_default_queue="svrobs",
        broker_connection_retry_on_startup=True,
        # a lost broker connection must not cancel running units (Celery 6's default):
        # they finish and store their results in the DB; a message the broker still
        # has is redelivered and skipped, one it lost is re-published by the relay
        worker_cancel_long_running_tasks_on_connection_loss=False,
        broker_connection_timeout=settings.BROKER_TIMEOUT,
        task_publish_retry_policy=PUBLISH_RETRY_POLICY,
        worker_hijack_root_logger=False,
        timezone="UTC",
        enable_utc=True,
    )
    if is_filesystem(settings.BROKER_URL):
        # kombu's filesystem transport with atomic writes and claims (service.file_broker)
        conf["broker_transport"] = FILE_TRANSPORT
        conf["broker_transport_options"] = {
            **_ensure_folders(settings),
            "store_processed": False,
            # kombu polls the folder when it has nothing to deliver (default every 1 s,
            # also while a prefetch-1 worker finishes a unit): 0.1 s keeps the gap
            # between units short for the cost of a directory listing
            "polling_interval": settings.BROKER_POLL_SECONDS,
        }
        # broadcast (remote control, mingle, gossip) is not reliable across processes on files
        conf["worker_enable_remote_control"] = False
    elif settings.BROKER_URL.startswith(("redis:", "rediss:")):
        # kombu's Redis transport, which sets aside what is not a message (service.redis_broker)
        conf["broker_transport"] = REDIS_TRANSPORT
        if (
            settings.BROKER_URL.startswith("rediss:")
            and "ssl_cert_reqs=" not in settings.BROKER_URL
        ):
            # TLS with the server's certificate checked (kombu alone, for the rediss scheme
            # only, falls back to TLS without any check); ?ssl_cert_reqs=none in the URL opts out
            conf["broker_use_ssl"] = {"ssl_cert_reqs": ssl.CERT_REQUIRED}
        conf["broker_transport_options"] = {
            # a unit not acked within this time is redelivered: keep it above the longest task
            "visibility_timeout": limit + 600,
            "socket_connect_timeout": settings.BROKER_TIMEOUT,
            "socket_timeout": max(5.0, settings.BROKER_TIMEOUT),
            "retry_on_timeout": True,
        }
    app.conf.update(conf)
    return app


def publish_units(
    celery: Celery, unit_ids: Iterable[int], *, raise_errors: bool = False
) -> list[int]:
    """Send one ``svrobs.run_unit(unit_id)`` task per unit; returns the ids sent.

    On a broker error the ids sent so far are returned (the caller marks those
    published; the relay sends the rest later) unless ``raise_errors``.
    """
    sent: list[int] = []
    ids = [int(u) for u in unit_ids]
    if not ids:
        return sent
    try:
        with celery.producer_or_acquire() as producer:
            _ensure_epoch_marker(celery, producer)
            for uid in ids:
                celery.send_task(
                    RUN_UNIT_TASK,
                    args=[uid],
                    producer=producer,
                    retry=True,
                    retry_policy=PUBLISH_RETRY_POLICY,
                )
                sent.append(uid)
    except Exception as exc:  # broker down: the relay re-publishes from the DB
        log.warning("publishing %d units failed after %d: %s", len(ids), len(sent), exc)
        if raise_errors:
            raise
    return sent


class BrokerPublisher:
    """``publisher(unit_ids) -> ids sent`` through one Celery app, made on first use
    for the settings ``settings_of()`` returns then; :meth:`get_celery` is that app
    (``/readyz`` checks its broker)."""

    def __init__(self, settings_of: Callable[[], Settings]):
        self._settings_of = settings_of
        self._celery: Celery | None = None

    def get_celery(self) -> Celery:
        if self._celery is None:
            self._celery = make_celery(self._settings_of())
        return self._celery

    def __call__(self, unit_ids: Iterable[int]) -> list[int]:
        return publish_units(self.get_celery(), unit_ids)


def check_broker(celery: Celery, timeout: float = 2.0) -> None:
    """Raise if the broker cannot be reached (used by /readyz)."""
    url = celery.conf.broker_url or ""
    if is_filesystem(url):
        opts = celery.conf.broker_transport_options or {}
        for key in ("data_folder_in", "data_folder_out"):
            path = opts.get(key)
            if not path or not os.path.isdir(path) or not os.access(path, os.W_OK):
                raise RuntimeError(f"broker folder {path!r} is missing or not writable")
        return
    with celery.connection_for_write() as conn:
        conn.ensure_connection(max_retries=1, timeout=timeout)
        if url.startswith(("redis:", "rediss:")):
            conn.default_channel.client.ping()


# A key kept in the broker's own Redis database, holding the time it was created.
# Queued messages and this key live and die together: when a Redis restarted without
# persistence (or flushed, or failed over to an empty replica) has lost the queue, the
# key is gone too. The relay then re-creates it and re-publishes every pending unit
# published before that time at once, instead of waiting PUBLISH_RETRY_SECONDS.
BROKER_EPOCH_KEY = "svrobs:broker-epoch"


def _redis_time(client) -> float:
    """The Redis server's clock (TIME), in seconds: the marker is written by the API
    and the relay on different hosts, so it never takes a host's local clock."""
    secs, usecs = client.time()
    return int(secs) + int(usecs) / 1e6


def _epoch_now(client) -> str:
    return repr(_redis_time(client))


def _ensure_epoch_marker(celery: Celery, producer) -> None:
    """Create the marker (if missing) before publishing: messages sent from now on
    belong to the broker's current data, so the relay does not take them for lost."""
    if not (celery.conf.broker_url or "").startswith(("redis:", "rediss:")):
        return
    try:
        client = producer.channel.client
        client.set(BROKER_EPOCH_KEY, _epoch_now(client), nx=True)
    except Exception as exc:  # noqa: BLE001 - the sends below report a dead broker
        log.debug("broker epoch marker not set: %s", exc)


def broker_epoch(celery: Celery, timeout: float = 2.0, *, now=None):
    """When the broker's current data began (a UTC datetime), creating the marker
    now if it is missing; None for a broker without one (the filesystem broker keeps
    its queue on disk). Raises if the broker cannot be reached.

    The marker is in the Redis server's clock; with ``now`` (the caller's clock, e.g.
    the database's) it is returned in that clock: ``now - (redis now - marker)``."""
    from datetime import UTC, datetime, timedelta

    url = celery.conf.broker_url or ""
    if not url.startswith(("redis:", "rediss:")):
        return None
    with celery.connection_for_write() as conn:
        conn.ensure_connection(max_retries=1, timeout=timeout)
        client = conn.default_channel.client
        client.set(BROKER_EPOCH_KEY, _epoch_now(client), nx=True)
        value = client.get(BROKER_EPOCH_KEY)
        redis_now = _redis_time(client) if now is not None else None
    if isinstance(value, bytes):
        value = value.decode()
    if now is None:
        return datetime.fromtimestamp(float(value), UTC)
    # redis_now was read because now is given
    return now - timedelta(seconds=max(cast(float, redis_now) - float(value), 0.0))
