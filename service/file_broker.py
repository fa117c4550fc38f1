"""The embedded broker: kombu's filesystem transport, made safe to share between processes.

Kombu's ``filesystem`` transport keeps one file per message in a folder. As shipped,
a publisher creates the file and then writes it, and a consumer that lists the
folder in between reads an empty file; the JSON error that follows stops the
worker. :class:`Transport` (what ``service.broker.make_celery`` selects for a
``filesystem://`` URL through Celery's ``broker_transport``) changes three things:

- a message is written to a hidden temporary file in the queue folder and renamed
  into place, so a consumer sees a whole message or none;
- a consumer claims a message by renaming it into the processed folder (one
  rename on one file system: exactly one consumer wins), reads it there, and a
  message it cannot decode into a kombu message is moved to the ``bad`` folder
  and logged, and the next message is taken: nothing on disk stops a worker (a
  message the worker drops, ``worker.message_guard``, is written there too);
- a new exchange table (the ``control`` folder) is written whole and linked into
  place; an unreadable one is rewritten with the binding being made;
- waiting for a message ends at the next poll once the worker is stopping: Celery's
  loop for a transport without a file descriptor checks for a shutdown only between
  waits of 2 s each, which made a stop take that much longer.

See docs/performance.md#embedded-broker for the measurements behind this choice.
"""

from __future__ import annotations

import logging
import os
import re
import socket
import uuid
from queue import Empty
from time import monotonic, monotonic_ns, sleep

from celery.worker import state
from kombu.exceptions import ChannelError
from kombu.transport import filesystem
from kombu.utils.encoding import str_to_bytes
from kombu.utils.json import dumps
from kombu.utils.objects import cached_property

from service.broker_messages import decode_message

log = logging.getLogger(__name__)

TRANSPORT = "service.file_broker:Transport"  # the name Celery's broker_transport takes
_QUEUE_NAME = re.compile(r"[A-Za-z0-9_-]{1,100}")


def _queue_of(name: str) -> str:
    """The queue a message file belongs to, the way kombu names them:
    ``<ms>_<uuid>.<queue>.msg``. Temporary files start with a dot and match no queue."""
    return name.partition(".")[2]


def _write_whole(folder: str, queue: str, payload) -> str:
    """Write ``payload`` as a message file of ``queue`` in ``folder``: to a hidden
    temporary file, renamed into place. Returns the file's path."""
    # zero-padded nanoseconds: names sort in publishing order (kombu: milliseconds,
    # unpadded, so messages of one millisecond and across a digit count were shuffled)
    name = f"{monotonic_ns():020d}_{uuid.uuid4()}.{queue}.msg"
    final = os.path.join(folder, name)
    tmp = os.path.join(folder, f".{name}.tmp")
    try:
        with open(tmp, "xb") as fh:
            fh.write(str_to_bytes(dumps(payload)))
        os.rename(tmp, final)
    except OSError:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return final


class Channel(filesystem.Channel):
    """A filesystem channel with atomic writes and claims and a folder for bad messages."""

    @cached_property
    def bad_folder(self) -> str:
        default = os.path.join(os.path.dirname(os.path.abspath(self.data_folder_in)), "bad")
        return self.transport_options.get("bad_folder", default)

    # ------------------------------------------------------------------ write
    def _put(self, queue, payload, **kwargs):
        try:
            _write_whole(self.data_folder_out, queue, payload)
        except OSError as exc:
            raise ChannelError(f"Cannot add file to {self.data_folder_out!r}: {exc}") from exc

    def keep_bad_message(self, message) -> str:
        """Write a delivered message the worker dropped (``worker.message_guard``) to the
        bad folder, as it was queued; returns its path (OSError if it cannot)."""
        os.makedirs(self.bad_folder, exist_ok=True)
        queue = (message.delivery_info or {}).get("routing_key")
        if not (isinstance(queue, str) and _QUEUE_NAME.fullmatch(queue)):
            queue = "unknown"  # the name becomes part of a path
        return _write_whole(self.bad_folder, queue, message.serializable())

    # ------------------------------------------------------------------ read
    def _get(self, queue):
        wanted = f"{queue}.msg"
        names = sorted(n for n in os.listdir(self.data_folder_in) if _queue_of(n) == wanted)
        for name in names:
            claimed = os.path.join(self.processed_folder, name)
            try:
                os.rename(os.path.join(self.data_folder_in, name), claimed)
            except FileNotFoundError:
                continue  # another consumer claimed it
            except OSError as exc:
                log.warning("broker message %s not claimed: %s", name, exc)
                continue
            try:
                with open(claimed, "rb") as fh:
                    data = fh.read()
            except OSError as exc:
                raise ChannelError(f"Cannot read file {claimed!r} from queue.") from exc
            payload = self._decode(claimed, data)
            if payload is None:
                continue
            if not self.store_processed:
                os.remove(claimed)
            return payload
        raise Empty()

    def _decode(self, path: str, data: bytes):
        """The message in ``data``, or None after moving the file to the bad folder."""
        payload, reason = decode_message(self, data)
        if reason is not None:
            self._set_aside(path, reason, len(data))
        return payload

    def _set_aside(self, path: str, reason: str, size: int) -> None:
        name = os.path.basename(path)
        target = os.path.join(self.bad_folder, name)
        try:
            os.makedirs(self.bad_folder, exist_ok=True)
            os.replace(path, target)
        except OSError as exc:
            log.error(
                "broker message %s (%d bytes) is not a message (%s); removing it: %s",
                name,
                size,
                reason,
                exc,
            )
            try:
                os.remove(path)
            except OSError:
                pass
            return
        log.error(
            "broker message %s (%d bytes) is not a message (%s); moved to %s",
            name,
            size,
            reason,
            target,
        )

    # ------------------------------------------------------------------ bindings
    def _queue_bind(self, exchange, routing_key, pattern, queue):
        file = self._exchange_file(exchange)
        entry = [filesystem.exchange_queue_t(routing_key or "", pattern or "", queue or "")]
        if not file.exists():
            self.control_folder.mkdir(exist_ok=True)
            if self._write_table(file, entry, replace=False):
                return
        try:
            super()._queue_bind(exchange, routing_key, pattern, queue)
        except ValueError as exc:  # the table is not JSON
            log.error("exchange table %s unreadable (%s); rewritten", file, exc)
            self._write_table(file, entry, replace=True)

    def _write_table(self, file, entries, *, replace: bool) -> bool:
        """Write ``entries`` whole to a temporary file and put it at ``file``; without
        ``replace``, False if ``file`` appeared meanwhile (it is left as it is)."""
        tmp = file.with_name(f".{file.name}.{uuid.uuid4().hex}.tmp")
        tmp.write_bytes(str_to_bytes(dumps(entries)))
        try:
            if replace:
                os.replace(tmp, file)
            else:
                os.link(tmp, file)
            return True
        except FileExistsError:
            return False
        finally:
            tmp.unlink(missing_ok=True)


def _stopping() -> bool:
    """Whether this process is a Celery worker that was told to stop (warm or cold),
    read as ``celery.worker.state.maybe_shutdown`` reads it."""
    flags = (state.should_stop, state.should_terminate)  # an exit code: 0 is a stop
    return any(flag is not None and flag is not False for flag in flags)


class Transport(filesystem.Transport):
    Channel = Channel

    def drain_events(self, connection, timeout=None):
        """Kombu's wait for a message (poll, sleep one polling interval, poll again
        until ``timeout``), which also gives up (``socket.timeout``, what the worker's
        loop expects) after a poll that finds nothing once the worker is stopping."""
        step = self.polling_interval
        if timeout is None or not step:
            return super().drain_events(connection, timeout=timeout)
        deadline = monotonic() + timeout
        while True:
            try:
                self.cycle.get(self._deliver, timeout=timeout)
                return None
            except Empty:
                left = deadline - monotonic()
                if left <= 0 or _stopping():
                    raise socket.timeout() from None
                sleep(min(step, left))
