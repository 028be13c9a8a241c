"""Which sensor is which: a pinned serial number checked whenever the identity is read.

USB adapters renumber after a reboot; when two lines share formats and addresses, every
request still gets an answer, from the other line's sensor. A device with
``serial_number:`` pinned is published only once the serial it reports is the pinned one,
read at start and after every reconnection or return online (the identity points are
re-read then, :meth:`~gateway.line.engine.schedule.Schedule.restart_device`).

Until then its samples are held back and its coming online is not announced. On another
serial (or none readable) the device is *held*: offline with a reason that says so, no
values published, no command's read or write let through, and no polling but a read of
the serial number alone on the probe backoff, for a swapped adapter may be swapped back.
The right serial releases it, polled in full again. The first verdict of a streak is an
ERROR with both serials and the remedy; repeats are DEBUG; the release is INFO. Devices
without a pin pass through untouched.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from enum import StrEnum
from typing import TYPE_CHECKING

from gateway.errors import (
    BusTimeoutError,
    CommandRejectedError,
    DeviceExceptionError,
    FrameError,
)
from gateway.line.samples import Quality
from gateway.profiles.serial_number import answered_text, serial_point

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from gateway.line.engine.devices import DeviceState
    from gateway.line.engine.health import Announce, Availability, DeviceHealth
    from gateway.line.engine.schedule import Schedule
    from gateway.line.engine.transactions import Transactions
    from gateway.line.samples import Sample
    from gateway.profiles import Point
    from gateway.profiles.serial_number import PinnedSerial

_LOGGER = logging.getLogger(__name__)


class IdentityVerdict(StrEnum):
    """What the line knows of a device's identity (``/healthz``, the metrics)."""

    UNPINNED = "unpinned"  # no serial_number: any sensor at the address is taken
    UNCONFIRMED = "unconfirmed"  # pinned, not read since start, reconnection or offline
    CONFIRMED = "confirmed"  # the pinned serial answered
    MISMATCH = "mismatch"  # another serial answered: held
    UNREAD = "unread"  # the serial could not be read (exception, no answer): held


@dataclass(slots=True)
class Pin:
    """One pinned device's identity as the line knows it."""

    expected: PinnedSerial
    point: Point
    verdict: IdentityVerdict = IdentityVerdict.UNCONFIRMED
    answered: str | None = None  # the serial (or failure) last read, as shown
    held: bool = False  # polling stopped; the serial is read again on the probe backoff
    since: datetime | None = None  # when the hold began
    deferred: str | None = None  # the reason of an "online" event held back until confirmed


class IdentityGuard:
    """The pinned serial numbers of one line's devices, checked where they are read."""

    def __init__(
        self,
        *,
        bus: str,
        devices: Mapping[str, DeviceState],
        transactions: Transactions,
        availability: Availability,
        schedule: Schedule,
        announce: Announce,
    ) -> None:
        """Guard the pinned devices of ``devices``; ``announce`` sends events to the sinks."""
        self.bus = bus
        self.transactions = transactions
        self.availability = availability
        self.schedule = schedule
        self._announce = announce
        self._pins: dict[str, Pin] = {}
        for state in devices.values():
            self.add(state)

    # --- a reload's changes ------------------------------------------------------------

    def add(self, state: DeviceState, *, keep: Pin | None = None) -> None:
        """Guard a device if its serial is pinned; ``keep``: its verdict before a re-plan.

        A re-planned device pinned to the same serial keeps its verdict: it is the same
        sensor, and its writes (a calibration under way) are not refused meanwhile.
        """
        expected = state.target.serial_number
        point = serial_point(state.profile)
        if expected is None or point is None:
            return
        if keep is not None and keep.expected == expected and keep.point == point:
            self._pins[state.target.name] = keep
        else:
            self._pins[state.target.name] = Pin(expected=expected, point=point)

    def remove(self, device: str) -> Pin | None:
        """Stop guarding a device (a reload removed or re-plans it); its pin, if it had one."""
        return self._pins.pop(device, None)

    # --- what the worker asks ----------------------------------------------------------

    def screens(self, state: DeviceState) -> bool:
        """Whether the device's samples go through :meth:`screen` (its serial is pinned)."""
        return state.target.name in self._pins

    def holds(self, state: DeviceState) -> bool:
        """Whether the device is held (another serial, or none): only its serial is read."""
        pin = self._pins.get(state.target.name)
        return pin is not None and pin.held

    def announces(self, state: DeviceState, *, online: bool, reason: str) -> bool:
        """Whether an availability event of the device goes to the sinks now.

        Offline: yes, and the identity is to be read again (unless the device is held,
        whose own offline event said why already). Online: not before the pinned serial
        has answered; the event is sent when it does.
        """
        pin = self._pins.get(state.target.name)
        if pin is None:
            return True
        if not online:
            if not pin.held:
                pin.verdict = IdentityVerdict.UNCONFIRMED
                pin.deferred = None
            return True
        if pin.verdict is IdentityVerdict.CONFIRMED:
            return True
        pin.deferred = reason
        return False

    def require_expected(self, device: str) -> None:
        """Refuse a command's read or write of a pinned device not confirmed.

        It may be another sensor, whose values would be shown, or which would be written
        to, under this device's name.
        """
        pin = self._pins.get(device)
        if pin is None or pin.verdict is IdentityVerdict.CONFIRMED:
            return
        if pin.verdict is IdentityVerdict.MISMATCH:
            why = (
                f"{device} is not the configured sensor: serial number {pin.answered} "
                f"answers, {pin.expected} is pinned"
            )
        else:
            why = (
                f"{device}: its pinned serial number {pin.expected} is not confirmed, so "
                "it may be another sensor"
            )
        raise CommandRejectedError(f"{why}; nothing is read from it or written to it")

    async def screen(self, state: DeviceState, samples: Sequence[Sample]) -> Sequence[Sample]:
        """The samples of a poll cycle that may be published: all of them, or none.

        A serial number read in the cycle is judged here; a pinned device's samples go
        out only while its pinned serial is confirmed.
        """
        pin = self._pins.get(state.target.name)
        if pin is None:
            return samples
        serial = next((s for s in samples if s.point == pin.point.name), None)
        if serial is not None:
            if serial.quality is Quality.COMMS_ERROR:
                if state.presence.online is not False:  # it answers the rest, not its serial
                    await self._hold(state, pin, IdentityVerdict.UNREAD, serial.fault or "")
                return ()
            value = state.values.get(pin.point.name)
            if not pin.expected.matches(value):
                await self._hold(state, pin, IdentityVerdict.MISMATCH, answered_text(value))
                return ()
            await self._confirm(state, pin, answered_text(value))
        return samples if pin.verdict is IdentityVerdict.CONFIRMED else ()

    async def recheck(self, state: DeviceState, now: float) -> None:
        """Read the serial number of a held device, and release it if it is the pinned one."""
        pin = self._pins[state.target.name]
        reads = self.transactions
        block = reads.plans.plan_points(state, [pin.point])[0]
        request = reads.requests.read(state, block)
        try:
            response = await reads.transact(state, request, 5 + 2 * block.count)
        except DeviceExceptionError as exc:
            self._still_held(state, pin, IdentityVerdict.UNREAD, f"exception_{exc.code:02d}", now)
            return
        except (BusTimeoutError, FrameError) as exc:
            _LOGGER.debug("%s/%s: identity check: %s", self.bus, state.target.name, exc)
            self.availability.probe_unanswered(state, now)
            return
        reads.decoder.decode(state, block, response.registers)
        value = state.values.get(pin.point.name)
        if pin.expected.matches(value):
            await self._release(state, pin, answered_text(value))
        else:
            self._still_held(state, pin, IdentityVerdict.MISMATCH, answered_text(value), now)

    def annotate(self, health: list[DeviceHealth]) -> list[DeviceHealth]:
        """The devices' health with their identity verdicts and serials (for the metrics)."""
        return [
            replace(
                entry,
                identity=pin.verdict.value,
                expected_serial=str(pin.expected),
                answered_serial=pin.answered,
            )
            if (pin := self._pins.get(entry.device)) is not None
            else entry
            for entry in health
        ]

    # --- verdicts ----------------------------------------------------------------------

    async def _hold(
        self, state: DeviceState, pin: Pin, verdict: IdentityVerdict, answered: str
    ) -> None:
        """Stop publishing and polling the device; say why, loudly, once per streak."""
        new_streak = not pin.held or pin.verdict is not verdict or pin.answered != answered
        pin.verdict, pin.answered = verdict, answered
        self._log(state, pin, loud=new_streak)
        if not pin.held:
            pin.held = True
            pin.since = datetime.now(tz=UTC)
        self.availability.hold(state)
        pin.deferred = None
        await self._announce(state, online=False, reason=self._reason(pin))

    def _still_held(
        self, state: DeviceState, pin: Pin, verdict: IdentityVerdict, answered: str, now: float
    ) -> None:
        """A held device's check found no pinned serial again: the next check later."""
        new_streak = pin.verdict is not verdict or pin.answered != answered
        pin.verdict, pin.answered = verdict, answered
        self._log(state, pin, loud=new_streak)
        self.availability.probe_unanswered(state, now)

    async def _confirm(self, state: DeviceState, pin: Pin, answered: str) -> None:
        """The pinned serial answered in a poll: publish, and say the device is online."""
        was = pin.verdict
        pin.verdict, pin.answered = IdentityVerdict.CONFIRMED, answered
        if was is IdentityVerdict.CONFIRMED:
            return
        _LOGGER.debug("%s/%s: serial number %s confirmed", self.bus, state.target.name, answered)
        if pin.deferred is not None and state.presence.online is True:
            reason, pin.deferred = pin.deferred, None
            await self._announce(state, online=True, reason=reason)

    async def _release(self, state: DeviceState, pin: Pin, answered: str) -> None:
        """The pinned serial answers again: the device is polled in full and published."""
        _LOGGER.info(
            "%s/%s (address %d): serial number %s answers again: it is the configured "
            "sensor; polling and publishing it again",
            self.bus,
            state.target.name,
            state.target.address,
            answered,
        )
        pin.verdict, pin.answered = IdentityVerdict.CONFIRMED, answered
        pin.held, pin.since, pin.deferred = False, None, None
        await self.availability.probe_answered(state, f"serial number {answered} confirmed")

    def _reason(self, pin: Pin) -> str:
        """The availability reason of a held device (MQTT, ``/healthz``)."""
        if pin.verdict is IdentityVerdict.MISMATCH:
            return (
                f"not the configured sensor: serial number {pin.answered} answered, "
                f"{pin.expected} is pinned"
            )
        return f"identity not confirmed: its serial number could not be read ({pin.answered})"

    def _log(self, state: DeviceState, pin: Pin, *, loud: bool) -> None:
        """The first verdict of a streak at ERROR, with both serials and the remedy."""
        log = _LOGGER.error if loud else _LOGGER.debug
        target = state.target
        if pin.verdict is IdentityVerdict.MISMATCH:
            log(
                "%s/%s (address %d): serial number %s answered, but serial_number pins %s: "
                "another sensor answers at this address, so nothing is published for it and "
                "nothing written to it. If the USB adapters swapped after a reboot, give each "
                "bus its /dev/serial/by-id/... name as port (ls -l /dev/serial/by-id); if the "
                "sensor was replaced, set serial_number: %s. Checking again on the probe "
                "backoff",
                self.bus,
                target.name,
                target.address,
                pin.answered,
                pin.expected,
                _quoted(pin.answered),
            )
        else:
            log(
                "%s/%s (address %d): its serial number could not be read (%s), so it cannot "
                "be told from another sensor: nothing is published for it until serial "
                "number %s is read; check the profile and the device. Checking again on the "
                "probe backoff",
                self.bus,
                target.name,
                target.address,
                pin.answered,
                pin.expected,
            )


def _quoted(answered: str | None) -> str:
    """A serial as it goes into YAML: in double quotes, so no digits turn into a number."""
    return '"' + (answered or "").replace("\\", "\\\\").replace('"', '\\"') + '"'
