"""A scan of one line from the page: its polling paused while the scan has the port.

The scan is ``gateway scan``'s (:func:`gateway.line.scan.scan`), in the line's configured
format, over the addresses asked for. The line's :class:`BusWorker` lets go of the port
for it (:meth:`BusWorker.paused`) and takes it back when the scan ends, fails or is
stopped; while it runs, the page says that the line's values are not being read.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from gateway.errors import CommandRejectedError, GatewayError
from gateway.line.scan import parse_addresses, scan

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from gateway.line.engine.worker import BusWorker
    from gateway.line.transports.port_access import PortOptions
    from gateway.wire.timing import LineFormat

_LOGGER = logging.getLogger(__name__)


@dataclass(slots=True, kw_only=True)
class ScanJob:
    """One scan of one line: who asked, how far it got, what it found."""

    bus: str
    who: str
    addresses: tuple[int, ...]
    started: float = field(default_factory=time.monotonic)
    probed: int = 0
    found: int = 0
    running: bool = True
    report: dict[str, object] | None = None
    error: str | None = None
    task: asyncio.Task[None] | None = None

    def as_dict(self) -> dict[str, object]:
        """What the page shows of it."""
        return {
            "bus": self.bus,
            "who": self.who,
            "running": self.running,
            "probed": self.probed,
            "total": len(self.addresses),
            "found": self.found,
            "elapsed_s": round(time.monotonic() - self.started, 1),
            "report": self.report,
            "error": self.error,
        }


class LineScans:
    """The scans of the gateway's lines: one per line at a time, the last one kept."""

    def __init__(
        self,
        workers: Sequence[BusWorker],
        formats: Mapping[str, LineFormat],
        *,
        options: Mapping[str, PortOptions] | None = None,
        timeout_s: float | None = None,
    ) -> None:
        """Scan the lines of ``workers``, each in its configured format (by bus name).

        ``options``: how each bus's serial port is opened (its RS485 mode), by bus name, as
        the bus worker opens it.
        """
        self.workers = {worker.name: worker for worker in workers}
        self.formats = formats
        self.options = options or {}
        self.timeout_s = timeout_s
        self.jobs: dict[str, ScanJob] = {}

    def retarget(
        self,
        workers: Mapping[str, BusWorker],
        *,
        formats: Mapping[str, LineFormat],
        options: Mapping[str, PortOptions],
    ) -> None:
        """The lines to scan after a reload: the running workers, their formats and options.

        A scan under way keeps the worker it paused until it ends.
        """
        self.workers = dict(workers)
        self.formats = formats
        self.options = options
        for bus in [bus for bus in self.jobs if bus not in self.workers]:
            job = self.jobs[bus]
            if job.task is None or job.task.done():
                del self.jobs[bus]

    def paused(self) -> dict[str, str]:
        """The lines whose polling is paused now, and why."""
        return {
            name: worker.paused_for
            for name, worker in self.workers.items()
            if worker.paused_for is not None
        }

    def latest(self, bus: str) -> ScanJob | None:
        """The line's running or last scan."""
        return self.jobs.get(bus)

    def start(self, bus: str, who: str, addresses: str = "1-247") -> ScanJob:
        """Start scanning ``bus`` in a task; refused while it is scanned already."""
        worker = self.workers.get(bus)
        if worker is None:
            raise CommandRejectedError(f"no line {bus!r}")
        if (job := self.jobs.get(bus)) is not None and job.running:
            raise CommandRejectedError(f"{bus} is being scanned by {job.who}")
        try:
            wanted = parse_addresses(addresses)
        except GatewayError as exc:
            raise CommandRejectedError(str(exc)) from exc
        job = ScanJob(bus=bus, who=who, addresses=wanted)
        self.jobs[bus] = job
        _LOGGER.warning("web: %s scans line %s: its polling is paused", who, bus)
        job.task = asyncio.create_task(self._run(worker, job), name=f"web.scan[{bus}]")
        return job

    async def _run(self, worker: BusWorker, job: ScanJob) -> None:
        def progress(_format: LineFormat, _address: int, found: int) -> None:
            job.probed += 1
            job.found = found

        try:
            async with worker.paused(f"scanned from the web page by {job.who}"):
                report = await scan(
                    worker.line.port,
                    formats=(self.formats[job.bus],),
                    addresses=job.addresses,
                    timeout_s=self.timeout_s,
                    progress=progress,
                    options=self.options.get(job.bus),
                )
            job.report = report.as_dict()
            job.found = len(report.devices)
            _LOGGER.info("web: scan of %s found %d device(s)", job.bus, len(report.devices))
        except GatewayError as exc:
            job.error = str(exc)
            _LOGGER.warning("web: scan of %s failed: %s", job.bus, exc)
        finally:
            job.running = False

    async def close(self) -> None:
        """Stop scans still running (the lines go back to polling)."""
        tasks = [j.task for j in self.jobs.values() if j.task is not None and not j.task.done()]
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.wait(tasks, timeout=5.0)
