"""Requests per second from each source address: what one other master may ask of the process.

Every request costs the gateway's process something, a refusal or a cache hit as much as
a read that goes to the line (whose bus time the share already bounds); the event loop
that answers them also polls the lines. A token bucket per source address, of a second's
worth, lets a client's burst through and holds the rest: the connection waits for its
next token and reads nothing meanwhile, so a pipelining client waits in TCP's buffers.
A request whose turn would come later than the client may wait (``max_wait``: a rate
below one per ``max_wait``, or several connections of one address taking turns) is shed:
its connection waits ``max_wait`` all the same, then answers exception 06.

Pure: the time is passed in.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

MAX_ADDRESSES: Final = 1024  # buckets kept; full ones are dropped beyond this


@dataclass(slots=True)
class _Bucket:
    rate: float
    tokens: float  # negative: tokens already promised to waiting requests
    at: float

    def refill(self, now: float) -> None:
        self.tokens = min(self.capacity, self.tokens + (now - self.at) * self.rate)
        self.at = now

    @property
    def capacity(self) -> float:
        return max(1.0, self.rate)  # a second's worth, and at least one request


class Throttle:
    """The rate limit of every source address (:meth:`reserve` per request)."""

    def __init__(self, *, max_wait_s: float) -> None:
        """Requests that would wait longer than ``max_wait_s`` are shed."""
        self.max_wait_s = max_wait_s
        self._buckets: dict[str, _Bucket] = {}

    def reserve(self, host: str, rate: float, now: float) -> float | None:
        """The seconds the request must wait for its token (taken); ``None``: shed it (no token).

        Tokens are promised in the order requests ask, so connections of one address
        take turns.
        """
        bucket = self._buckets.get(host)
        if bucket is None:
            self._forget_full(now)
            bucket = self._buckets[host] = _Bucket(rate=rate, tokens=max(1.0, rate), at=now)
        bucket.rate = rate
        bucket.refill(now)
        wait = 0.0 if bucket.tokens >= 1 else (1 - bucket.tokens) / rate
        if wait > self.max_wait_s:
            return None
        bucket.tokens -= 1
        return wait

    def _forget_full(self, now: float) -> None:
        """Drop the buckets that refilled (their addresses asked nothing for a while)."""
        if len(self._buckets) < MAX_ADDRESSES:
            return
        for host, bucket in list(self._buckets.items()):
            bucket.refill(now)
            if bucket.tokens >= bucket.capacity:
                del self._buckets[host]
