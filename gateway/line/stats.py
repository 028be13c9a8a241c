"""What a line counts: transactions, failures by kind, latency, the port's state.

Apart from any kind of line so that the publishers (the state, the metrics, the page)
read a line's counters without importing a serial port: every line (serial, RTU over TCP,
Modbus TCP) keeps one :class:`LineStats` and counts its failures by :class:`ErrorKind`.
"""

from __future__ import annotations

import bisect
import math
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from typing import Final

from gateway.errors import (
    CrcError,
    EchoMismatchError,
    MalformedFrameError,
    UnexpectedDeviceError,
)

LATENCY_BUCKETS_S: Final = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)
_LATENCY_BOUNDS: Final = (*LATENCY_BUCKETS_S, math.inf)


class ErrorKind:
    """Names of the failure classes counted per bus and device."""

    TIMEOUT: Final = "timeout"
    CRC: Final = "crc"
    EXCEPTION: Final = "exception"
    WRONG_ADDRESS: Final = "wrong_address"
    STALE: Final = "stale_frame"
    NOISE: Final = "noise"
    MALFORMED: Final = "malformed"
    ECHO: Final = "echo"  # an echo of the request although the bus is set to ``echo: off``
    ECHO_MISMATCH: Final = "echo_mismatch"  # ``echo: on`` and what came back was not the request
    NO_SILENCE: Final = "no_silence"  # the line never fell silent: the request was not sent


_KIND_OF_FAILURE: Final[tuple[tuple[type[Exception], str], ...]] = (
    (EchoMismatchError, ErrorKind.ECHO_MISMATCH),
    (CrcError, ErrorKind.CRC),
    (UnexpectedDeviceError, ErrorKind.WRONG_ADDRESS),
    (MalformedFrameError, ErrorKind.MALFORMED),
)


def failure_kind(exc: Exception, *, otherwise: str) -> str:
    """The kind a failed answer is counted as; ``otherwise`` for any other failure."""
    for failure, kind in _KIND_OF_FAILURE:
        if isinstance(exc, failure):
            return kind
    return otherwise


@dataclass(slots=True)
class LineStats:
    """Counters of one line, per device address where it matters. Read by the sinks."""

    requests: Counter[int] = field(default_factory=Counter)
    responses: Counter[int] = field(default_factory=Counter)
    errors: Counter[tuple[int, str]] = field(default_factory=Counter)
    exception_codes: Counter[tuple[int, int]] = field(default_factory=Counter)
    retries: Counter[int] = field(default_factory=Counter)
    tolerated: Counter[tuple[int, str]] = field(default_factory=Counter)
    # Requests per device and latency bucket, not cumulative (the last: beyond the last
    # bound): one increment of a plain int per answer; the histogram is summed up when
    # it is read (:attr:`latency_buckets`), at a scrape, not on every transaction.
    latency_counts: dict[int, list[int]] = field(default_factory=dict)
    latency_sum_s: defaultdict[int, float] = field(default_factory=lambda: defaultdict(float))
    busy_s: float = 0.0  # time the line carried our transactions
    started: float = field(default_factory=time.monotonic)
    port_open: bool = False
    port_failures: int = 0
    noisy: str | None = None  # why the last request could not go out, while the line is noisy
    port_problem: str | None = None  # why the port is not open (port_diagnosis.PortReason)
    port_error: str = ""  # the message that says so, with its remedy
    latency_timer_s: float | None = None  # an FTDI adapter's latency timer, when read

    def closed_because(self, reason: str | None, message: str) -> None:
        """The port is not open, for this reason (``None``: no problem, it is opening)."""
        self.port_open = False
        self.port_problem = reason
        self.port_error = message

    def answered(self, device: int, seconds: float, tolerated: str | None) -> None:
        """A device answered after ``seconds`` (``tolerated``: a quirk of its answer let pass)."""
        self.responses[device] += 1
        self.observe_latency(device, seconds)
        if tolerated is not None:
            self.tolerated[device, tolerated] += 1

    def observe_latency(self, device: int, seconds: float) -> None:
        """Add one request-to-response time to the histogram."""
        self.latency_sum_s[device] += seconds
        counts = self.latency_counts.get(device)
        if counts is None:
            counts = self.latency_counts[device] = [0] * (len(LATENCY_BUCKETS_S) + 1)
        counts[bisect.bisect_left(LATENCY_BUCKETS_S, seconds)] += 1

    @property
    def latency_buckets(self) -> Counter[tuple[int, float]]:
        """The cumulative histogram: requests answered within each bound, per device.

        Keyed ``(device, bound)`` with ``math.inf`` for all of them; a bound no answer
        came within is left out. Safe to call from another thread (a scrape): each copy
        it takes is one step under the interpreter's lock.
        """
        buckets: Counter[tuple[int, float]] = Counter()
        for device, counts in list(self.latency_counts.items()):
            total = 0
            for bound, count in zip(_LATENCY_BOUNDS, tuple(counts), strict=True):
                total += count
                if total:
                    buckets[device, bound] = total
        return buckets

    def utilisation(self, now: float | None = None) -> float:
        """Share of wall time the line was busy with our transactions."""
        elapsed = (now if now is not None else time.monotonic()) - self.started
        return min(1.0, self.busy_s / elapsed) if elapsed > 0 else 0.0
