"""One device on a line, as commands, feeds, operations and calibrations see it.

A :class:`DeviceLink` reads and writes points through the line's
:class:`~gateway.line.engine.worker.BusWorker`, so every timing rule (gaps, post-write waits,
late-answer windows) still holds: while the gateway polls, its reads and writes queue
ahead of due polls; from the command line, with no poll running, they run at once.

A name is looked up in the profile once, where it comes in (:meth:`DeviceLink.read` for
reads by name); from there down the :class:`~gateway.profiles.model.Point` travels, so the
line never resolves a name again. Code that holds the point already (a write's read-back,
the bits to keep, a flash point's current value) reads it with
:meth:`DeviceLink.read_points` and looks nothing up.

Values are checked and encoded by :func:`gateway.control.commands.validate_write` before anything
is queued, in the word order the device uses now (its format register is read first if
need be), so a rejected value never reaches the bus.
"""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING

from gateway.config.echo import EchoMode
from gateway.control.commands import require_writable, validate_write
from gateway.errors import BusError
from gateway.line.engine.worker import BusWorker
from gateway.line.samples import Quality
from gateway.line.transports.factory import build_line
from gateway.wire.codec import DataType

if TYPE_CHECKING:
    from collections.abc import AsyncIterator

    from gateway.config.network import TcpSettings
    from gateway.line.engine.devices import DeviceTarget
    from gateway.line.transports.port_access import PortOptions
    from gateway.profiles import Profile
    from gateway.profiles.model import Point
    from gateway.wire import codec
    from gateway.wire.timing import LineFormat


class DeviceLink:
    """Reads and writes of one device's points, through its line's worker."""

    def __init__(self, worker: BusWorker, device: str) -> None:
        """Link to ``device`` on ``worker``'s line (a :class:`GatewayError` if it is not there)."""
        self.worker = worker
        self.device = device
        self.profile: Profile = worker.device_profile(device)
        self.address = worker.device_address(device)

    @property
    def bus(self) -> str:
        """The name of the line the device is on."""
        return self.worker.name

    async def float_order(self) -> codec.WordOrder:
        """The device's float word order, reading its format register first if not yet known."""
        if self.worker.needs_float_order(self.device):
            selector = self.profile.float_order_register
            assert selector is not None  # noqa: S101 - needs_float_order says there is one
            await self.read(selector.point)
        return self.worker.float_order(self.device)

    async def read(self, *names: str) -> dict[str, codec.Decoded]:
        """Read points by name now: each name looked up once, here (see :meth:`read_points`).

        An unknown name is a :class:`~gateway.errors.ConfigError` listing close ones,
        before anything is queued.
        """
        return await self.read_points(*(self.profile.point(name) for name in names))

    async def read_points(self, *points: Point) -> dict[str, codec.Decoded]:
        """Read points of the device's profile now, by name in the result.

        A :class:`BusError` names the points that could not be read. A sensor fault
        (``2.0e37``...) is a value here (:class:`codec.Fault`), not an error.
        """
        samples = await self.worker.read_points(self.device, points)
        failed = [s for s in samples if s.quality is Quality.COMMS_ERROR]
        if failed:
            what = ", ".join(f"{s.point} ({s.fault})" for s in failed)
            raise BusError(f"{self.device}: could not read {what}")
        if len(samples) != len(points):
            missing = sorted({p.name for p in points} - {s.point for s in samples})
            raise BusError(f"{self.device}: could not read {', '.join(missing)}")
        # A fault sample carries the fault's name; the decoded value keeps it with its raw.
        return {s.point: self.worker.last_value(self.device, s.point) for s in samples}

    async def read_value(self, name: str) -> codec.Decoded:
        """Read one point by name now."""
        return (await self.read(name))[name]

    async def read_point(self, point: Point) -> codec.Decoded:
        """Read one point of the device's profile now."""
        return (await self.read_points(point))[point.name]

    async def encode(self, point: Point, value: object) -> tuple[int, ...]:
        """The registers that write ``value`` to ``point``, or a :class:`CommandRejectedError`.

        ``point`` is one of the device's, resolved once where its name came in
        (:func:`gateway.control.commands.writable_point`). The value is checked before
        anything is read: bad input never reaches the bus, not even as the read of the
        float format register a float needs.
        """
        known = self.worker.float_order(self.device)
        registers = validate_write(self.profile, point, value, float_order=known)
        if point.format.dtype is DataType.FLOAT32:
            order = await self.float_order()
            if order is not known:
                registers = validate_write(self.profile, point, value, float_order=order)
        return registers

    async def write(self, point: Point, value: object) -> tuple[int, ...]:
        """Check, encode and write a value (06 or 16), keeping the post-write wait.

        Returns the registers written. Flash protection is the caller's:
        :class:`gateway.control.writes.SafeWriter` for commands and feeds.
        """
        registers = await self.encode(point, value)
        await self.write_registers(point, registers)
        return registers

    async def write_registers(self, point: Point, registers: tuple[int, ...]) -> None:
        """Write registers already checked and encoded (see :meth:`encode`)."""
        await self.worker.write_registers(self.device, require_writable(point), registers)


@contextlib.asynccontextmanager
async def open_link(
    port: str,
    line_format: LineFormat,
    target: DeviceTarget,
    *,
    echo: EchoMode = EchoMode.AUTO,
    options: PortOptions | None = None,
    tcp: TcpSettings | None = None,
) -> AsyncIterator[DeviceLink]:
    """Open the port for one device (the command line: no polling) and close it after.

    ``echo`` is the bus's setting (``off``, ``on``, ``auto``) and ``tcp`` its session
    settings, from the config if the device came from one. A serial port is opened
    exclusively: with the gateway polling it, this fails at once with a
    :class:`~gateway.errors.PortUnavailableError` that says what to stop.
    """
    line = build_line(port=port, line=line_format, tcp=tcp, echo=echo, options=options)
    await line.open()
    try:
        yield DeviceLink(BusWorker(name="cli", line=line, devices=[target]), target.name)
    finally:
        await line.close()
