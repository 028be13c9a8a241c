"""Writes that are safe: checked, flash-guarded, written with the rules, and read back.

:class:`SafeWriter` is the one path by which commands (MQTT ``…/set``, ``gateway write``)
and feeds change a device's registers:

0. the point is resolved by name once, where the name comes in (:meth:`SafeWriter.point`),
   and the :class:`~gateway.profiles.model.Point` is what every step below is given; a
   point that reaches a date-and-time register (a clock, a calibration stamp) is refused
   while the host clock is not trusted (:mod:`gateway.control.clock_trust`);
1. the value is checked and encoded for the point (:func:`gateway.control.commands.validate_write`);
   a bit field given as an object of bit names changes those bits only: the word is read
   and the other bits, named or not, are written back as the device holds them;
2. a flash-backed point is read first and judged by :func:`gateway.control.flash.check_flash_write`
   (allowed by name, unchanged values skipped, the daily budget), and an accepted flash
   write is counted in the persistent ledger *before* it is sent, on the disk itself (a
   power cut after the write cannot leave it uncounted; a ledger that cannot be written
   refuses the write, tests/app/test_power_cut.py and tests/app/test_full_disk.py);
3. the write is recorded (:mod:`gateway.records`) before it is sent: who asked
   (:func:`gateway.records.actor.current`), the device with the serial number it reports,
   the point's value as found; a record that cannot be written refuses the write;
4. the registers go out with function 06 or 16, and the post-write wait is kept;
5. the point is read back, so the caller sees what the device now holds, and the record's
   outcome says what it was left at (or why the write failed).

Anything refused in steps 1 to 3 raises :class:`CommandRejectedError` and nothing is sent.
Compensation feeds to volatile registers, which write every few seconds, are counted per
device and day (:class:`gateway.records.feeds.FeedCounts`) instead of recorded one by one.
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.config import FlashPolicy
from gateway.control.clock_trust import require_trusted_for
from gateway.control.commands import writable_point
from gateway.control.flash import Action, check_flash_write, utc_today
from gateway.control.recorded import WriteRecorder
from gateway.errors import (
    BusError,
    CommandRejectedError,
    DeviceExceptionError,
    EncodeError,
    GatewayError,
)
from gateway.profiles.model import Storage
from gateway.records.model import Result, json_decoded
from gateway.shared.host_clock import HostClock
from gateway.wire import codec, encoding

if TYPE_CHECKING:
    from collections.abc import Callable
    from datetime import date

    from gateway.control.flash import FlashLedger
    from gateway.control.link import DeviceLink
    from gateway.profiles.model import Point
    from gateway.records.feeds import FeedCounts
    from gateway.records.model import Record
    from gateway.records.store import RecordStore


@dataclass(frozen=True, slots=True, kw_only=True)
class WriteOutcome:
    """What became of an accepted write.

    ``written`` is false when a flash-backed point already held the value; ``value`` is
    what the device holds afterwards (read back), ``None`` if the read-back failed, in
    which case ``note`` says why.
    """

    device: str
    point: str
    written: bool
    value: codec.Decoded
    registers: tuple[int, ...]
    flash: bool
    note: str = ""
    record: int | None = None  # the number of the write's record, if it was recorded


UNANSWERED: Final = (
    "whether the sensor took the value is not known (the request may have reached it): "
    "read the point to see"
)


class SafeWriter:
    """The write path of one device, with its flash policy and the shared ledger."""

    def __init__(
        self,
        link: DeviceLink,
        *,
        policy: FlashPolicy,
        ledger: FlashLedger,
        today: Callable[[], date] = utc_today,
        clock: HostClock | None = None,
        records: RecordStore | None = None,
        feeds: FeedCounts | None = None,
    ) -> None:
        """Write to ``link``'s device under ``policy``, counting flash writes in ``ledger``.

        ``clock`` is the host clock that dates may be written by (the gateway's own, with
        the config's override; by default the kernel's word and the environment's).
        ``records``: where every write is recorded (``None``: nowhere, for a write that
        cannot touch a sensor's settings, such as a test's); ``feeds``: where compensation
        feeds are counted.
        """
        self.link = link
        self.policy = policy
        self.ledger = ledger
        self.clock = clock if clock is not None else HostClock()
        self.records = records
        self.recorder = WriteRecorder(link, records) if records is not None else None
        self.feeds = feeds
        self._today = today

    @property
    def device(self) -> str:
        """The device written to."""
        return self.link.device

    def point(self, name: str) -> Point:
        """The device's point of that name if it may be written (where a name comes in).

        A :class:`CommandRejectedError` for an unknown or read-only point, with the reason
        a set command's result carries.
        """
        return writable_point(self.link.profile, name)

    async def set(
        self,
        point: Point,
        value: object,
        *,
        explicit: bool = False,
        read_back: bool = True,
        feed: bool = False,
    ) -> WriteOutcome:
        """Write ``value`` to ``point`` if every rule allows it; see the module docstring.

        ``point`` is one of the device's, resolved once where its name came in
        (:meth:`point`). ``explicit`` is for an operator's deliberate step (a calibration,
        setting the clock): a flash-backed point needs no place in the allow-list and is
        written even if unchanged (writing the tecLine date stamp again is what activates a
        calibration), but the daily budget still holds and the write is still counted.
        ``read_back=False`` saves the read-back (feeds, which write often). ``feed``: a
        compensation feed, counted per day rather than recorded when the point is volatile.
        """
        link = self.link
        name = point.name
        require_trusted_for(self.clock, link.profile, point, f"writing {name} of {link.device}")
        registers = await link.encode(point, value)  # refuses bad input before any read
        if isinstance(value, Mapping) and point.format.dtype in codec.BITFIELD_TYPES:
            registers = await link.encode(point, await self._merged_bits(point, value))
        flash = point.storage is Storage.FLASH
        current: codec.Decoded = None
        held: tuple[int, ...] | None = None
        policy = self.policy
        if flash and explicit:
            policy = FlashPolicy(allowed=policy.allowed | {name}, daily_budget=policy.daily_budget)
        elif flash and name in policy.allowed:
            current, held = await self._current(point)
        decision = check_flash_write(
            point,
            link.device,
            policy=policy,
            ledger=self.ledger,
            current=held,
            registers=registers,
            today=self._today(),
        )
        if decision.action is Action.REFUSE:
            raise CommandRejectedError(decision.reason, point=name)
        if decision.action is Action.SKIP:
            return WriteOutcome(
                device=link.device,
                point=name,
                written=False,
                value=current,
                registers=registers,
                flash=flash,
                note=decision.reason,
            )
        found = (current, "") if held is not None else None
        return await self._send(
            point,
            value,
            registers,
            found=found,
            count_flash=decision.record,
            read_back=read_back,
            feed=feed,
        )

    async def _send(
        self,
        point: Point,
        value: object,
        registers: tuple[int, ...],
        *,
        found: tuple[codec.Decoded, str] | None,
        count_flash: bool,
        read_back: bool,
        feed: bool,
    ) -> WriteOutcome:
        """Steps 3 to 5: record (and count a flash write), send, read back, record the outcome.

        ``found``: the value as found if it was read already (a flash point's check).
        """
        link = self.link
        flash = point.storage is Storage.FLASH
        counted = feed and not flash
        if count_flash:  # counted first: a write that is then not recorded counts once more
            self.ledger.record(link.device, point.name, self._today())
        recorder = None if counted else self.recorder
        pending = None
        if recorder is not None:
            pending = await recorder.write(
                point, value, registers, found or await recorder.as_found(point)
            )
        await self._write(point, registers, recorder, pending)
        if counted and self.feeds is not None:
            self.feeds.count(link.device, point.name)
        note = ""
        after: codec.Decoded = None
        if read_back:
            try:
                after = await link.read_point(point)
            except BusError as exc:
                note = f"written; the read-back failed: {exc}"
        if recorder is not None and pending is not None:
            left = json_decoded(after) if read_back and not note else None
            said = note or ("" if read_back else "written; not read back (a step of a sequence)")
            recorder.outcome(pending, point, Result.DONE, note=said, as_left=left)
        return WriteOutcome(
            device=link.device,
            point=point.name,
            written=True,
            value=after,
            registers=registers,
            flash=flash,
            note=note,
            record=None if pending is None else pending.seq,
        )

    async def _write(
        self,
        point: Point,
        registers: tuple[int, ...],
        recorder: WriteRecorder | None,
        pending: Record | None,
    ) -> None:
        """Send the registers; a failure's outcome recorded before it is raised.

        Refused by the sensor (an exception answer): failed, nothing changed. No answer, or
        the caller gave up waiting (a command's timeout): unknown, since the request may
        have reached the sensor.
        """
        try:
            await self.link.write_registers(point, registers)
        except DeviceExceptionError as exc:
            if recorder is not None and pending is not None:
                recorder.outcome(pending, point, Result.FAILED, note=str(exc))
            raise
        except (GatewayError, asyncio.CancelledError) as exc:
            if recorder is not None and pending is not None:
                said = str(exc) or "the request was cancelled while it waited for the answer"
                recorder.outcome(pending, point, Result.UNKNOWN, note=f"{said}; {UNANSWERED}")
            raise

    async def _merged_bits(self, point: Point, bits: Mapping[object, object]) -> int:
        """The word the device holds with the named ``bits`` set or cleared.

        A plant system that sends ``{"salinity_from_ram": true}`` means that bit, not "clear
        every other": the rest of the word (the bits the profile does not name included,
        e.g. the S10 control byte's bits 4-7) is kept as read.
        """
        try:
            held = await self.link.read_point(point)
        except BusError as exc:
            raise CommandRejectedError(
                f"could not read the bits to keep, so nothing was written: {exc}",
                point=point.name,
            ) from exc
        if not isinstance(held, codec.BitfieldValue):
            raise CommandRejectedError(
                f"the bits to keep read as {held!r}, so nothing was written", point=point.name
            )
        return encoding.with_bits(point.format, held.raw, bits)

    async def _current(self, point: Point) -> tuple[codec.Decoded, tuple[int, ...] | None]:
        """What a flash-backed point holds, decoded and as registers to compare with."""
        try:
            current = await self.link.read_point(point)
        except BusError as exc:
            raise CommandRejectedError(
                f"could not read the current value before a flash write, so nothing was "
                f"written: {exc}",
                point=point.name,
            ) from exc
        try:
            held = encoding.encode(point.format, current, float_order=await self.link.float_order())
        except EncodeError:
            held = None  # a fault value or an unknown code: compare nothing, write
        return current, held
