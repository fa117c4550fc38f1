"""uvicorn's HTTP protocol (httptools) with deadlines on each request's headers and
body, and a size limit on its headers (docs/security.md#slow-or-large-requests).

uvicorn times out an idle kept-alive connection, but not one that is sending a
request: a client that opens connections and sends a byte of header or body now and
then (slowloris) holds each open for as long as it likes, until the process has no
file descriptors left; and httptools reads headers of any size.

Headers. A connection closes when a request's headers are not complete
``SVROBS_HEADER_TIMEOUT_SECONDS`` (10 s) after they became due, or when more than
``MAX_HEADER_BYTES`` (64 KiB, give or take one read) arrive before they are
complete. The next request's headers are due once the previous request has arrived
whole (or the connection opened). Their bytes are counted from then on, also while
that request is being answered (a pipelined request's headers cannot grow without
bound meanwhile); their deadline runs only once its answer is complete as well,
so that neither a long computation nor a client still sending a body that was
answered early (a 413) is cut off.

Body. Once a request's headers are complete, its body must have arrived whole by a
deadline ``SVROBS_BODY_TIMEOUT_SECONDS`` (20 s) away, which each body byte moves
``1 / SVROBS_BODY_MIN_BYTES_PER_SECOND`` s later (500 bytes/s: a 100 MB upload at
that rate is never cut off), as Apache's mod_reqtimeout does. While the server does
not read (uvicorn pauses reading when the app has not taken 64 KiB of body yet, or
while it answers an earlier pipelined request), or has not yet answered a client's
``Expect: 100-continue``, the client cannot send: the deadline is kept at least the
full timeout away then, and from the moment the client can send again.

Every entry point serves the API with it:
``uvicorn ... --http service.http.request_deadlines:RequestDeadlineProtocol``
(``svrobs serve``, the image, docker-compose)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable

from uvicorn.protocols.http.flow_control import FlowControl
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.config import get_settings

log = logging.getLogger(__name__)

PROTOCOL = f"{__name__}:RequestDeadlineProtocol"  # uvicorn's --http value
MAX_HEADER_BYTES = 64 * 1024  # a request line and headers: h11's limit (16 KiB) x 4


class _Flow(FlowControl):
    """uvicorn's flow control, telling its protocol whenever reading resumes."""

    def __init__(self, transport: asyncio.Transport, on_resume: Callable[[bool], None]) -> None:
        super().__init__(transport)
        self._on_resume = on_resume

    def resume_reading(self) -> None:
        self._on_resume(self.read_paused)
        super().resume_reading()


class RequestDeadlineProtocol(HttpToolsProtocol):
    """:class:`HttpToolsProtocol` that closes a connection whose request headers are
    late or too large, or whose request body is late."""

    _headers_due: asyncio.TimerHandle | None = None
    _awaiting = False  # the previous request arrived whole: the next one's headers are due
    _header_bytes = 0  # received since then, in reads in which no headers completed
    _headers_seen = 0  # requests whose headers were complete, so far
    _body_due: asyncio.TimerHandle | None = None
    _body_deadline = 0.0  # loop time by which the request's body must be whole
    _expects_continue = False  # the request's client waits for a 100 Continue

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self.flow = _Flow(transport, self._reading_resumed)
        self._await_headers(deadline=True)

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_deadline()
        self._stop_body()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        awaiting, seen = self._awaiting, self._headers_seen
        super().data_received(data)
        # a read made while headers were due, in which none completed: all header bytes
        if not (awaiting and self._awaiting and self._headers_seen == seen):
            return
        self._header_bytes += len(data)
        if self._header_bytes > MAX_HEADER_BYTES and not self.transport.is_closing():
            self._close(f"request headers over {MAX_HEADER_BYTES} bytes")

    def on_headers_complete(self) -> None:
        self._headers_seen += 1
        self._awaiting = False
        self._stop_deadline()
        super().on_headers_complete()
        if self._upgrading():
            return  # a WebSocket: the connection goes to another protocol, untimed
        seconds = get_settings().BODY_TIMEOUT_SECONDS
        self._stop_body()  # one body timed at a time: this request's
        self._expects_continue = self.expect_100_continue
        self._body_deadline = self.loop.time() + seconds
        self._body_due = self.loop.call_later(seconds, self._body_check)

    def on_body(self, body: bytes) -> None:
        self._body_deadline += len(body) / get_settings().BODY_MIN_BYTES_PER_SECOND
        super().on_body(body)

    def on_message_complete(self) -> None:
        self._stop_body()
        super().on_message_complete()
        if self._upgrading():
            return  # a WebSocket: the connection goes to another protocol, untimed
        answered = self.cycle is not None and self.cycle.response_complete
        self._await_headers(deadline=answered)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        # the latest request answered too (uvicorn may have just started a pipelined one)
        answered = self.cycle is not None and self.cycle.response_complete
        if answered and self._awaiting and self._headers_due is None:
            if not self.transport.is_closing():
                self._start_deadline()

    def _upgrading(self) -> bool:
        """The request upgrades the connection to a WebSocket (uvicorn's own test)."""
        return bool(self.parser.should_upgrade() and self._should_upgrade())

    def _reading_resumed(self, paused: bool) -> None:
        """The client may send again (reading resumes, or its 100 Continue is sent):
        the body it is sending gets at least the full timeout from now."""
        continued = self._expects_continue and not (
            self.cycle is not None and self.cycle.waiting_for_100_continue
        )
        if (paused or continued) and self._body_due is not None:
            self._expects_continue = False
            seconds = get_settings().BODY_TIMEOUT_SECONDS
            self._body_deadline = max(self._body_deadline, self.loop.time() + seconds)

    def _await_headers(self, *, deadline: bool) -> None:
        self._awaiting = True
        self._header_bytes = 0
        self._stop_deadline()
        if deadline:
            self._start_deadline()

    def _start_deadline(self) -> None:
        seconds = get_settings().HEADER_TIMEOUT_SECONDS
        self._headers_due = self.loop.call_later(seconds, self._headers_late, seconds)

    def _stop_deadline(self) -> None:
        if self._headers_due is not None:
            self._headers_due.cancel()
            self._headers_due = None

    def _headers_late(self, seconds: float) -> None:
        self._headers_due = None
        if self._awaiting and not self.transport.is_closing():
            self._close(f"no complete request headers in {seconds:g} s")

    def _stop_body(self) -> None:
        if self._body_due is not None:
            self._body_due.cancel()
            self._body_due = None

    def _body_check(self) -> None:
        """At the body's deadline as it was when this was scheduled: close the
        connection if it has passed and the client could send meanwhile."""
        self._body_due = None
        if self.transport.is_closing():
            return
        settings, now = get_settings(), self.loop.time()
        waiting = self.cycle is not None and self.cycle.waiting_for_100_continue
        if waiting or (self.flow is not None and self.flow.read_paused):  # the client waits
            self._body_deadline = max(self._body_deadline, now + settings.BODY_TIMEOUT_SECONDS)
        left = self._body_deadline - now
        if left > 0:
            self._body_due = self.loop.call_later(left, self._body_check)
            return
        self._close(
            f"request body not whole in {settings.BODY_TIMEOUT_SECONDS:g} s "
            f"plus 1 s per {settings.BODY_MIN_BYTES_PER_SECOND:g} bytes received"
        )

    def _close(self, why: str) -> None:
        self._stop_deadline()
        self._stop_body()
        log.info("closed a connection from %s: %s", self.client, why)
        self.transport.close()
