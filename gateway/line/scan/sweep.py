"""The whole scan: each line format in turn on one port, every address probed in each."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from gateway.config import MAX_RESPONSE_TIMEOUT_S
from gateway.errors import ConfigError
from gateway.line.scan.probe import Scanner
from gateway.line.scan.report import FoundDevice, ScanReport
from gateway.line.transports.factory import build_line

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from gateway.line.boundary import Line
    from gateway.line.transports.port_access import PortOptions
    from gateway.wire.timing import LineFormat


async def scan(
    port: str,
    *,
    formats: Sequence[LineFormat],
    addresses: Sequence[int],
    timeout_s: float | None = None,
    progress: Callable[[LineFormat, int, int], None] | None = None,
    line_factory: Callable[..., Line] = build_line,
    options: PortOptions | None = None,
) -> ScanReport:
    """Open ``port`` in each format in turn and probe every address.

    ``progress(format, address, found_so_far)`` is called after each address, with the
    devices found in all formats so far. A port that
    cannot be opened raises :class:`gateway.errors.BusClosedError` before anything is sent.
    ``line_factory(port=..., line=...)`` builds each :class:`Line` (a seam for tests);
    ``options`` (a configured bus's RS485 mode and shared-bus hints) are passed on to it.
    """
    if timeout_s is not None and not 0 < timeout_s <= MAX_RESPONSE_TIMEOUT_S:
        raise ConfigError(
            f"--timeout {timeout_s:g}: expected more than 0 and at most "
            f"{MAX_RESPONSE_TIMEOUT_S:g} s"
        )
    started = time.monotonic()
    devices: list[FoundDevice] = []
    garbled: list[tuple[LineFormat, int]] = []
    requests = 0
    for fmt in formats:
        line = (
            line_factory(port=port, line=fmt)
            if options is None
            else line_factory(port=port, line=fmt, options=options)
        )
        await line.open()
        try:
            scanner = Scanner(line, timeout_s=timeout_s)

            def report(
                address: int, found: int, fmt: LineFormat = fmt, before: int = len(devices)
            ) -> None:
                if progress is not None:
                    progress(fmt, address, before + found)

            devices.extend(await scanner.sweep(addresses, progress=report))
            garbled.extend((fmt, address) for address in scanner.garbled)
        finally:
            requests += sum(line.stats.requests.values())
            await line.close()
    return ScanReport(
        port=port,
        formats=tuple(formats),
        addresses=tuple(addresses),
        devices=tuple(devices),
        garbled=tuple(garbled),
        requests=requests,
        elapsed_s=time.monotonic() - started,
    )
