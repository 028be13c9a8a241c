"""A reload's new set of devices for a running line, applied between transactions.

The worker asks for a change (:meth:`DeviceChanges.request`) at any time; the change is
applied only where nothing of the worker walks the devices: before its next step, or at
once while it sleeps, backs off or is paused. Each device's fate is decided here and
carried out by the parts that own its state: the schedule, the transactions, the identity
guard, the queues of writes and of other masters' requests.
"""

from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING

from gateway.errors import GatewayError
from gateway.line.engine.devices import DeviceState

if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.line.engine.devices import DeviceTarget
    from gateway.line.engine.foreign import ForeignQueue
    from gateway.line.engine.identity_guard import IdentityGuard, Pin
    from gateway.line.engine.jobs import JobQueue
    from gateway.line.engine.schedule import Schedule
    from gateway.line.engine.transactions import Transactions


class DeviceChanges:
    """The reload's changes of one line's devices, queued until the worker may apply them."""

    def __init__(
        self,
        *,
        bus: str,
        devices: dict[str, DeviceState],
        schedule: Schedule,
        transactions: Transactions,
        identity: IdentityGuard,
        jobs: JobQueue,
        foreign: ForeignQueue,
    ) -> None:
        """Change ``devices`` (the worker's, shared by its parts) through the parts given."""
        self.bus = bus
        self.devices = devices
        self.schedule = schedule
        self.transactions = transactions
        self.identity = identity
        self.jobs = jobs
        self.foreign = foreign
        self._pending: list[tuple[tuple[DeviceTarget, ...], asyncio.Future[None]]] = []

    def __bool__(self) -> bool:
        """Whether a change waits to be applied."""
        return bool(self._pending)

    def request(self, targets: Sequence[DeviceTarget]) -> asyncio.Future[None]:
        """Queue ``targets`` as the line's devices; the future is done once applied."""
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._pending.append((tuple(targets), done))
        return done

    def apply(self) -> None:
        """Apply every queued change, oldest first."""
        while self._pending:
            targets, done = self._pending.pop(0)
            self._change_devices(targets)
            if not done.done():
                done.set_result(None)

    def _change_devices(self, targets: Sequence[DeviceTarget]) -> None:
        """A device whose target is unchanged keeps everything; see ``BusWorker.change_devices``."""
        wanted = {target.name: target for target in targets}
        for name in [name for name in self.devices if name not in wanted]:
            self._remove_device(name, f"{self.bus}/{name} was removed from the config")
        now = time.monotonic()
        for target in targets:
            former = self.devices.get(target.name)
            if former is not None and former.target == target:
                continue
            if former is None:
                self._add_device(DeviceState(target=target), now)
            elif former.target.address == target.address and former.profile is target.profile:
                self._replan_device(former, target, now)
            else:
                self._remove_device(target.name, f"{self.bus}/{target.name} is another sensor now")
                self._add_device(DeviceState(target=target), now)

    def _remove_device(self, name: str, reason: str) -> None:
        """A device that goes: its queued work fails with ``reason``."""
        gone = GatewayError(reason)
        self.jobs.fail_device(name, gone)
        self.foreign.fail_device(name, gone)
        self._forget_device(self.devices.pop(name))

    def _forget_device(self, state: DeviceState) -> Pin | None:
        """Out of the schedule, the plans and the pins (its queued work untouched)."""
        self.schedule.remove(state)
        self.transactions.remove(state)
        return self.identity.remove(state.target.name)

    def _add_device(self, state: DeviceState, now: float, pin: Pin | None = None) -> None:
        self.devices[state.target.name] = state
        self.transactions.add(state)
        self.identity.add(state, keep=pin)
        self.schedule.add(state, now)

    def _replan_device(self, former: DeviceState, target: DeviceTarget, now: float) -> None:
        """The same sensor with other settings: new deadlines, what it is and said kept."""
        pin = self._forget_device(former)
        self._add_device(former.carried_over(target), now, pin)
