"""Device health on one line: which devices answer, the offline verdict and the probes.

A device is online from its first answer (an exception is an answer too) and goes offline
after ``offline_after`` failed transactions in a row; an offline device is probed on a
capped, jittered backoff and polled in full again once it answers. Every change is an event
to the sinks. :class:`DeviceHealth` is what the metrics and ``/healthz`` read of it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    import random
    from collections.abc import Mapping

    from gateway.line.engine.devices import DeviceState
    from gateway.line.engine.schedule import Schedule

_LOGGER = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True, kw_only=True)
class DeviceHealth:
    """A device as its bus task sees it: availability, poll lag, missed deadlines."""

    bus: str
    device: str
    address: int
    online: bool | None
    failures_in_a_row: int
    lag_s: float
    missed_deadlines: int
    unreadable_points: int
    # A pinned serial number's verdict (line/engine/identity_guard: unpinned, unconfirmed,
    # confirmed, mismatch, unread), the serial pinned and the one that answered last.
    identity: str = "unpinned"
    expected_serial: str | None = None
    answered_serial: str | None = None


class Announce(Protocol):
    """Tells the sinks that a device came online or went offline, and why."""

    async def __call__(self, state: DeviceState, *, online: bool, reason: str) -> None:
        """Send the device's event to every sink."""


class Availability:
    """The online/offline verdicts of one line's devices, and the pace of their probes."""

    def __init__(
        self,
        *,
        bus: str,
        devices: Mapping[str, DeviceState],
        schedule: Schedule,
        announce: Announce,
        rng: random.Random,
    ) -> None:
        """Judge ``devices`` of the line ``bus``; ``announce`` tells the sinks of changes."""
        self.bus = bus
        self.devices = devices
        self.schedule = schedule
        self._announce = announce
        self._rng = rng

    def answered_online(self, state: DeviceState) -> bool:
        """The device answered: its failures forgotten; whether it was online already.

        Nearly every answer; only one that is not needs :meth:`answered` (it announces), so
        a poll's path spares a coroutine per transaction.
        """
        presence = state.presence
        presence.failures = 0
        presence.backoff_s = 0.0
        return presence.online is True

    async def answered(self, state: DeviceState, reason: str) -> None:
        """The device answered: online (again, polled in full if it was offline)."""
        if self.answered_online(state):
            return
        presence = state.presence
        was_offline = presence.online is False
        presence.online = True
        if was_offline:
            _LOGGER.info("%s/%s is back online", self.bus, state.target.name)
            self.schedule.restart_device(state, time.monotonic())
        await self._announce(state, online=True, reason=reason)

    async def failed(self, state: DeviceState, reason: str) -> None:
        """One more failed transaction in a row; enough of them take the device offline."""
        presence = state.presence
        presence.failures += 1
        if presence.failures >= state.target.offline_after and presence.online is not False:
            self.hold(state)
            _LOGGER.warning(
                "%s/%s (address %d) is offline after %d failed requests: %s",
                self.bus,
                state.target.name,
                state.target.address,
                presence.failures,
                reason,
            )
            await self._announce(state, online=False, reason=reason)

    def probe_unanswered(self, state: DeviceState, now: float) -> None:
        """An offline device did not answer its probe: the next one later, jittered."""
        presence, target = state.presence, state.target
        cap = max(target.probe_max_s, target.poll_interval_s)
        presence.backoff_s = min(max(presence.backoff_s, target.poll_interval_s) * 2, cap)
        presence.probe_at = now + presence.backoff_s * self._rng.uniform(0.8, 1.2)

    async def probe_answered(self, state: DeviceState, reason: str = "answered a probe") -> None:
        """An offline (or held) device answered its probe: online, and polled in full again."""
        state.presence.online = None
        await self.answered(state, reason)
        self.schedule.restart_device(state, time.monotonic())

    def hold(self, state: DeviceState) -> None:
        """Offline, the first probe a poll interval from now.

        Also for a device that is not the configured sensor: the identity guard's check of
        its serial then comes at the probes' pace.
        """
        presence = state.presence
        presence.online = False
        presence.backoff_s = state.target.poll_interval_s
        presence.probe_at = time.monotonic() + presence.backoff_s
        self.schedule.touch(state)  # the probe may be due before its values were

    async def all_offline(self, reason: str) -> None:
        """The port is gone: every device is offline, to be probed as soon as it is back."""
        for state in self.devices.values():
            if state.presence.online is not False:
                state.presence.online = False
                state.presence.probe_at = 0.0
                self.schedule.touch(state)
                await self._announce(state, online=False, reason=reason)

    def health(self) -> list[DeviceHealth]:
        """Each device's availability, lag and missed deadlines (read by the metrics)."""
        return [
            DeviceHealth(
                bus=self.bus,
                device=name,
                address=state.target.address,
                online=state.presence.online,
                failures_in_a_row=state.presence.failures,
                lag_s=state.deadlines.lag_s,
                missed_deadlines=state.deadlines.missed_deadlines,
                unreadable_points=len(state.holds.unreadable),
            )
            for name, state in self.devices.items()
        ]
