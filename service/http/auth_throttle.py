"""Failed authentications per client address (docs/security.md#failed-authentications):
a token bucket of ``SVROBS_AUTH_FAILURES_PER_MINUTE`` per address, in one API
process. A failure (a bad key at sign-in or as a bearer key) takes a token; an
address with no token left is refused before its key is even looked up, with
:class:`~svrobs_lab.errors.RateLimited` (429, Retry-After: until a token is back),
so a guessed key is no more use than a wrong one."""

from __future__ import annotations

import ipaddress
import threading
import time

from svrobs_lab.errors import RateLimited

MAX_ADDRESSES = 100_000  # past this, addresses with a full bucket are dropped


class AuthThrottle:
    def __init__(self, per_minute: int):
        self.capacity = float(per_minute)
        self.rate = per_minute / 60.0
        self._buckets: dict[str, tuple[float, float]] = {}
        self._lock = threading.Lock()

    def _tokens(self, address: str, now: float) -> float:
        tokens, last = self._buckets.get(address, (self.capacity, now))
        return min(self.capacity, tokens + (now - last) * self.rate)

    def check(self, address: str) -> None:
        """RateLimited when ``address`` has used up its failures."""
        if self.rate <= 0:
            return
        with self._lock:
            tokens = self._tokens(address, time.monotonic())
        if tokens < 1.0:
            retry = max(1, int((1.0 - tokens) / self.rate + 0.999))
            raise RateLimited(
                "too many failed authentications from this address "
                "(SVROBS_AUTH_FAILURES_PER_MINUTE)",
                retry_after=retry,
            )

    def failed(self, address: str) -> None:
        """Count one failed authentication of ``address``."""
        if self.rate <= 0:
            return
        now = time.monotonic()
        with self._lock:
            if len(self._buckets) >= MAX_ADDRESSES:
                self._prune(now)
            self._buckets[address] = (max(0.0, self._tokens(address, now) - 1.0), now)

    def _prune(self, now: float) -> None:
        full = [a for a in self._buckets if self._tokens(a, now) >= self.capacity]
        for a in full or list(self._buckets)[: MAX_ADDRESSES // 2]:
            del self._buckets[a]


def client_address(request) -> str:
    """The request's peer address (uvicorn's ``--proxy-headers`` makes it the
    forwarded one behind a trusted proxy), as :func:`throttled_as` counts it."""
    return throttled_as(request.client.host if request.client is not None else "unknown")


def throttled_as(host: str) -> str:
    """The bucket of a peer: its IPv4 address (also when written IPv4-mapped, as
    ``::ffff:a.b.c.d``), or the /64 network of an IPv6 one (a host is routinely given
    a whole /64, so one bucket per address would let it spread its guesses over
    2^64 buckets); any other text as it is."""
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return host
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        return str(ipaddress.IPv6Network((ip, 64), strict=False))
    return str(ip)
