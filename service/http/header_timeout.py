"""uvicorn's HTTP protocol (httptools) with a deadline and a size limit on each
request's headers.

uvicorn times out an idle kept-alive connection, but not one that is sending a
request's headers: a client that opens connections and sends a byte of header now
and then (slowloris) holds each open for as long as it likes, until the process has
no file descriptors left; and httptools reads headers of any size. Here a
connection closes when a request's headers are not complete
``SVROBS_HEADER_TIMEOUT_SECONDS`` (10 s) after they became due, or when more than
``MAX_HEADER_BYTES`` (64 KiB, give or take one read) arrive before they are
complete (docs/security.md#slow-or-large-headers).

The next request's headers are due once the previous request has arrived whole
(or the connection opened). Their bytes are counted from then on, also while that
request is being answered (a pipelined request's headers cannot grow without
bound meanwhile); their deadline runs only once its answer is complete as well,
so that neither a long computation nor a client still sending a body that was
answered early (a 413) is cut off. Every entry point serves the API with it:
``uvicorn ... --http service.http.header_timeout:HeaderTimeoutProtocol``
(``svrobs serve``, the image, docker-compose)."""

from __future__ import annotations

import asyncio
import logging

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.config import get_settings

log = logging.getLogger(__name__)

PROTOCOL = f"{__name__}:HeaderTimeoutProtocol"  # uvicorn's --http value
MAX_HEADER_BYTES = 64 * 1024  # a request line and headers: h11's limit (16 KiB) x 4


class HeaderTimeoutProtocol(HttpToolsProtocol):
    """:class:`HttpToolsProtocol` that closes a connection whose request headers are
    late or too large."""

    _headers_due: asyncio.TimerHandle | None = None
    _awaiting = False  # the previous request arrived whole: the next one's headers are due
    _header_bytes = 0  # received since then, in reads in which no headers completed
    _headers_seen = 0  # requests whose headers were complete, so far

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._await_headers(deadline=True)

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_deadline()
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

    def on_message_complete(self) -> None:
        super().on_message_complete()
        answered = self.cycle is not None and self.cycle.response_complete
        self._await_headers(deadline=answered)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if self._awaiting and self._headers_due is None and not self.transport.is_closing():
            self._start_deadline()

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

    def _close(self, why: str) -> None:
        self._stop_deadline()
        log.info("closed a connection from %s: %s", self.client, why)
        self.transport.close()
