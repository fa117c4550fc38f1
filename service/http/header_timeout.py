"""uvicorn's HTTP protocol (httptools) with a deadline and a size limit on each
request's headers.

uvicorn times out an idle keep-alive connection, but not one that is sending a
request's headers: a client that opens connections and sends a byte of header now
and then (slowloris) holds each open for as long as it likes, until the process has
no file descriptors left. Here a connection closes when a request's headers are
not complete ``SVROBS_HEADER_TIMEOUT_SECONDS`` (10 s) after the connection opened or
after its previous response, or when they pass ``MAX_HEADER_BYTES`` (64 KiB;
httptools reads headers of any size) (docs/security.md#slow-or-large-headers). Every entry point
serves the API with it: ``uvicorn ... --http service.http.header_timeout:HeaderTimeoutProtocol``
(``svrobs serve``, the image, docker-compose)."""

from __future__ import annotations

import asyncio
import logging

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.config import get_settings

log = logging.getLogger(__name__)

PROTOCOL = f"{__name__}:HeaderTimeoutProtocol"  # uvicorn's --http value
MAX_HEADER_BYTES = 64 * 1024  # a request line and headers, as h11's limit (16 KiB) x 4


class HeaderTimeoutProtocol(HttpToolsProtocol):
    """:class:`HttpToolsProtocol` that closes a connection whose request headers are
    late."""

    _headers_due: asyncio.TimerHandle | None = None
    _header_bytes = 0  # received since the headers became due

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._await_headers()

    def connection_lost(self, exc: Exception | None) -> None:
        self._headers_arrived()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        super().data_received(data)  # parsing may complete the headers (then not counted)
        if self._headers_due is None or self.transport.is_closing():
            return
        self._header_bytes += len(data)
        if self._header_bytes > MAX_HEADER_BYTES:
            self._headers_arrived()
            log.info(
                "closed a connection from %s: request headers over %d bytes",
                self.client,
                MAX_HEADER_BYTES,
            )
            self.transport.close()

    def on_headers_complete(self) -> None:
        self._headers_arrived()
        super().on_headers_complete()

    def on_response_complete(self) -> None:
        idle = not self.pipeline  # no request read meanwhile: the next one's headers are due
        super().on_response_complete()
        if idle and not self.transport.is_closing():
            self._await_headers()

    def _await_headers(self) -> None:
        self._headers_arrived()
        self._header_bytes = 0
        seconds = get_settings().HEADER_TIMEOUT_SECONDS
        self._headers_due = self.loop.call_later(seconds, self._headers_late, seconds)

    def _headers_arrived(self) -> None:
        if self._headers_due is not None:
            self._headers_due.cancel()
            self._headers_due = None

    def _headers_late(self, seconds: float) -> None:
        self._headers_due = None
        if not self.transport.is_closing():
            log.info(
                "closed a connection from %s: no complete request headers in %g s",
                self.client,
                seconds,
            )
            self.transport.close()
