"""The Redis broker: kombu's Redis transport, which sets aside what is not a message.

Kombu's Redis channel takes a message off the queue's list (``BRPOP``) and decodes it
in the worker's event loop; bytes that are not a kombu envelope (anything pushed onto
the list by hand or by another program) raise there and end the worker.
:class:`Transport` (what ``service.broker.make_celery`` selects for a ``redis://`` URL
through Celery's ``broker_transport``) checks each item ``BRPOP`` returns with
:func:`service.broker_messages.decode_message`; one that fails is logged (one ERROR
line), pushed onto the list :data:`BAD_LIST` (the newest :data:`BAD_KEPT` are kept)
and skipped, as if the wait had ended empty. A synchronous get (``basic_get``, the
path of a ``SimpleQueue`` and of tools that poll) sets aside such items the same way
and returns the first message behind them. See docs/security.md#task-messages.
"""

from __future__ import annotations

import logging
from typing import Any

from kombu.transport import redis
from kombu.transport.virtual import Empty

from service.broker_messages import decode_message

log = logging.getLogger(__name__)

TRANSPORT = "service.redis_broker:Transport"  # the name Celery's broker_transport takes
BAD_LIST = "svrobs.bad"  # where items that are not messages are kept
BAD_KEPT = 1000


class Channel(redis.Channel):
    """A Redis channel whose ``BRPOP`` replies are checked before kombu decodes them."""

    def _create_client(self, asynchronous: bool = False) -> Any:
        client = super()._create_client(asynchronous=asynchronous)
        if asynchronous:  # the client that waits on BRPOP in the worker's loop
            read = client.parse_response

            def parse_response(connection: Any, command_name: str, **options: Any) -> Any:
                reply = read(connection, command_name, **options)
                if command_name == "BRPOP" and reply and not self._is_message(*reply):
                    return None  # kombu's _brpop_read: nothing arrived
                return reply

            client.parse_response = parse_response
        return client

    def _get(self, queue: str, timeout: Any = None) -> Any:
        """The next message on ``queue`` (kombu's ``_get``, each item checked): items
        that are not messages are set aside, the first message behind them returned."""
        with self.conn_or_acquire() as client:
            for pri in self.priority_steps:
                while item := client.rpop(self._q_for_pri(queue, pri)):
                    payload, reason = decode_message(self, item)
                    if reason is None:
                        self._maybe_update_queues_expire(client, queue)
                        return payload
                    self._set_aside(queue, item, reason, client)
            self._maybe_update_queues_expire(client, queue)
            raise Empty()

    def _is_message(self, key: bytes, item: bytes) -> bool:
        """Whether ``item`` (taken off the list ``key``) is a message; if not, it is
        set aside."""
        _, reason = decode_message(self, item)
        if reason is None:
            return True
        self._set_aside(key, item, reason)
        return False

    def _set_aside(self, key: bytes | str, item: bytes, reason: str, client: Any = None) -> None:
        """Log ``item`` (not a message, taken off the list ``key``) and keep it on
        :data:`BAD_LIST` (through ``client`` if one is in hand)."""
        where = f"kept on the list {BAD_LIST!r}"
        try:
            with self.conn_or_acquire(client) as bad:
                bad.lpush(BAD_LIST, item)
                bad.ltrim(BAD_LIST, 0, BAD_KEPT - 1)
        except Exception as exc:  # noqa: BLE001 - the item is dropped all the same
            where = f"not kept: {exc}"
        queue = key.decode(errors="replace") if isinstance(key, bytes) else str(key)
        log.error(
            "broker message on %r (%d bytes) is not a message (%s); %s",
            queue,
            len(item),
            reason,
            where,
        )


class Transport(redis.Transport):
    Channel = Channel
