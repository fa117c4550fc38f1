"""A task message the worker cannot run is dropped, instead of stopping the worker.

Celery's consumer turns only some faults of a task message into a log line (a body
that does not decode, a bad ETA); any other (no ``id`` header, a ``task`` header
that is not a string, a body that is not ``[args, kwargs, embed]``, a ``timelimit``
that is not two numbers) raises in the worker's main process and ends it, and the
unacknowledged message is delivered again to the next worker: a crash loop, or on
Redis a reconnect loop that runs nothing. :class:`Consumer` (what
``worker.celery_app`` sets as Celery's ``worker_consumer``) checks every task
message with :func:`problem` before Celery's handler sees it; a message that fails
is logged (one ERROR line: what is wrong and its id), acknowledged and dropped, and
on the embedded broker kept in the broker's ``bad`` folder
(:meth:`service.file_broker.Channel.keep_bad_message`). See
docs/security.md#task-messages.
"""

from __future__ import annotations

import logging
import math
from typing import Any

from celery import signals
from celery.utils.time import maybe_iso8601
from celery.worker.consumer import Consumer as CeleryConsumer
from kombu.exceptions import ContentDisallowed, DecodeError

log = logging.getLogger(__name__)

CONSUMER = "worker.message_guard:Consumer"  # the name Celery's worker_consumer takes


def _is_time_limit(value: Any) -> bool:
    if value is None:
        return True
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    return math.isfinite(value) and value >= 0


def _header_problem(headers: dict) -> str | None:
    """What in a protocol-2 message's headers Celery's worker cannot take, or None."""
    task = headers.get("task")
    if not isinstance(task, str) or not task:
        return f"header 'task' is {_short(task)}, not a task name"
    ident = headers.get("id")
    if not isinstance(ident, str) or not ident:
        return f"header 'id' is {_short(ident)}, not a non-empty string"
    limits = headers.get("timelimit")
    if limits is not None and not (
        isinstance(limits, (list, tuple)) and len(limits) == 2 and all(map(_is_time_limit, limits))
    ):
        return f"header 'timelimit' is {_short(limits)}, not two numbers >= 0 or nulls"
    for key in ("eta", "expires"):
        try:
            maybe_iso8601(headers.get(key))
        except (AttributeError, ValueError, TypeError, OverflowError):
            return f"header {key!r} is {_short(headers.get(key))}, not an ISO 8601 time"
    retries = headers.get("retries")
    if retries is not None and (type(retries) is not int or retries < 0):
        return f"header 'retries' is {_short(retries)}, not an integer >= 0"
    stamped = headers.get("stamped_headers")  # iterated in the main process (revoke check)
    if stamped is not None and not (
        isinstance(stamped, (list, tuple)) and all(isinstance(h, str) for h in stamped)
    ):
        return f"header 'stamped_headers' is {_short(stamped)}, not a list of names"
    stamps = headers.get("stamps")
    if stamps is not None and not isinstance(stamps, dict):
        return f"header 'stamps' is {_short(stamps)}, not an object"
    return None


def _body_problem(body: Any) -> str | None:
    if not (isinstance(body, (list, tuple)) and len(body) == 3):
        return f"body is {_short(body)}, not [args, kwargs, embed]"
    args, kwargs, embed = body
    if not isinstance(args, (list, tuple)):
        return f"body's args are {_short(args)}, not a list"
    if not isinstance(kwargs, dict):
        return f"body's kwargs are {_short(kwargs)}, not an object"
    if embed is not None and not isinstance(embed, dict):
        return f"body's embed is {_short(embed)}, not an object"
    return None


def problem(message) -> str | None:
    """Why Celery's worker cannot take ``message`` (a kombu message from a task queue),
    or None. A body that does not decode at all is left to Celery, which logs it and
    acknowledges it. Only protocol 2 (every Celery 4+ sender's) is accepted."""
    headers = message.headers
    if not isinstance(headers, dict):
        return f"headers are {_short(headers)}, not an object"
    if "task" not in headers:
        return "no 'task' header (not a protocol-2 task message)"
    found = _header_problem(headers)
    if found is not None:
        return found
    try:
        body = message.payload
    except (DecodeError, ContentDisallowed):
        return None
    except Exception as exc:  # noqa: BLE001 - a body kombu cannot even hand to Celery
        return f"body does not decode: {type(exc).__name__}: {str(exc)[:200]}"
    return _body_problem(body)


def _short(value: Any, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


class Consumer(CeleryConsumer):
    """Celery's consumer, whose task handler first drops the messages :func:`problem`
    finds fault with."""

    def create_task_handler(self, *args, **kwargs):
        on_task_received = super().create_task_handler(*args, **kwargs)

        def on_checked_task(message):
            reason = problem(message)
            if reason is None:
                return on_task_received(message)
            self._drop(message, reason)
            return None

        return on_checked_task

    def _drop(self, message, reason: str) -> None:
        headers = message.headers if isinstance(message.headers, dict) else {}
        ident = headers.get("id")
        name = f"task message {_short(ident)}" if ident else "task message without id"
        where = ""
        keep = getattr(message.channel, "keep_bad_message", None)
        if keep is not None:
            try:
                where = f"; kept in {keep(message)}"
            except Exception as exc:  # noqa: BLE001 - the message is dropped all the same
                where = f"; not kept: {exc}"
        log.error("%s dropped: %s%s", name, reason, where)
        message.ack_log_error(log, self.connection_errors)
        signals.task_rejected.send(sender=self, message=message, exc=None)
