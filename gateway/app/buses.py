"""The buses of the running gateway: their workers and tasks, and each device's write path.

:class:`Buses` holds what the config's ``buses:`` and ``devices:`` build, and changes it
in place for a reload (:meth:`Buses.change`, then :meth:`Buses.build` and
:meth:`Buses.start`): a bus that is gone stops; a bus that changed keeps its worker, which
takes its new devices between two frames and a new line through a pause
(:meth:`~gateway.line.engine.worker.BusWorker.change_devices`,
:meth:`~gateway.line.engine.worker.BusWorker.use_line`), so that what runs on it, a calibration
among it, goes on; a bus that is new is built and started. The ``workers`` and ``writers``
dictionaries are the same objects for the whole run: the page, the commands and the feeds
that hold them see the change.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from typing import TYPE_CHECKING

from gateway.app.build import (
    build_worker,
    build_writer,
    bus_line,
    bus_targets,
    care_for,
    device_target,
    register_device,
)
from gateway.app.tasks import SHUTDOWN_S, stop_tasks
from gateway.profiles import get_profile

if TYPE_CHECKING:
    from collections.abc import Callable

    from gateway.config import BusConfig, DeviceConfig, GatewayConfig
    from gateway.config.changes import ConfigChanges
    from gateway.control.flash import FlashLedger
    from gateway.control.writes import SafeWriter
    from gateway.line.engine.worker import BusWorker
    from gateway.line.samples import Sink
    from gateway.publish.mqtt import MqttSink
    from gateway.records import FeedCounts, RecordStore
    from gateway.shared.state import GatewayState

_LOGGER = logging.getLogger(__name__)


class Buses:
    """Every bus of one config, its worker and task, and every device's write path."""

    def __init__(
        self,
        config: GatewayConfig,
        state: GatewayState,
        ledger: FlashLedger,
        sinks: Callable[[], list[Sink]],
        *,
        records: RecordStore | None = None,
        feeds: FeedCounts | None = None,
    ) -> None:
        """Build a worker per bus and a write path per device; ``sinks``: asked per build.

        ``records``: where every write path records its writes; ``feeds``: where
        compensation feeds are counted.
        """
        self.config = config
        self.state = state
        self.ledger = ledger
        self.records = records
        self.feed_counts = feeds
        self._sinks = sinks
        self.workers: dict[str, BusWorker] = {
            bus.name: build_worker(config, bus, sinks(), state) for bus in config.buses
        }
        self.writers: dict[str, SafeWriter] = {
            device.name: self._writer(device, self.workers[device.bus]) for device in config.devices
        }
        self._tasks: dict[str, asyncio.Task[None]] = {}

    def _writer(self, device: DeviceConfig, worker: BusWorker) -> SafeWriter:
        """A device's write path, recording into the run's records."""
        return build_writer(
            device,
            worker,
            self.ledger,
            self.state.clock,
            records=self.records,
            feeds=self.feed_counts,
        )

    # --- start and stop ----------------------------------------------------------------

    async def claim_ports(self) -> None:
        """Open every port before anything else starts: another master on one stops a start."""
        for worker in self.workers.values():
            await worker.claim_port()

    def start(self) -> None:
        """Start the workers that do not run yet."""
        for name, worker in self.workers.items():
            if name not in self._tasks:
                self._tasks[name] = asyncio.create_task(worker.run(), name=f"bus[{name}]")

    def tasks(self) -> list[asyncio.Task[None]]:
        """The workers' tasks: one's ending is the gateway's failure."""
        return list(self._tasks.values())

    async def stop(self) -> None:
        """Every worker after the frame in flight, within ``SHUTDOWN_S``; then cancelled."""
        for worker in self.workers.values():
            worker.request_stop()
        tasks = list(self._tasks.values())
        if tasks:
            await asyncio.wait(tasks, timeout=SHUTDOWN_S)
        await stop_tasks(tasks)

    async def close_lines(self) -> None:
        """Close every port (the end of the run)."""
        for worker in self.workers.values():
            await worker.line.close()

    # --- a reload ----------------------------------------------------------------------

    async def change(
        self, changes: ConfigChanges, old: GatewayConfig, mqtt: MqttSink | None
    ) -> set[str]:
        """Stop the buses that go, change those that changed in their running workers.

        Then forget the devices that went (after their worker stopped polling them, so
        that no late sample brings their retained topics back) and those now on another
        bus or at another address or of another profile; and show the devices that
        changed or came. A bus whose worker cannot change (its line is paused for a scan)
        is stopped, its name returned: :meth:`build` builds it anew.
        """
        new = self.config
        rebuilt: set[str] = set()
        for name in changes.buses_removed:
            await self._stop_bus(name)
        for name in changes.buses_changed:
            if not await self._change_bus(name, old):
                await self._stop_bus(name)
                rebuilt.add(name)
        if mqtt is not None:
            self._announce_changed(changes, old, mqtt)
        stopped = {*changes.buses_removed, *rebuilt}
        after = {device.name: device for device in new.devices}
        for device in old.devices:
            now = after.get(device.name)
            if now is None:
                self._forget_device(device.bus, device.name, mqtt)
            elif device.bus in stopped or _another_sensor(device, now):
                self.state.remove_device(device.bus, device.name)
        self._show_changed(changes, rebuilt)
        return rebuilt

    def _show_changed(self, changes: ConfigChanges, rebuilt: set[str]) -> None:
        """The devices changed or added on a changed bus: shown, cared for, written to anew.

        Those on a bus built anew are its builder's (:meth:`build`).
        """
        touched = {*changes.devices_changed, *changes.devices_added}
        for device in self.config.devices:
            if device.name not in touched or device.bus not in changes.buses_changed:
                continue
            if device.bus in rebuilt:
                continue
            worker = self.workers[device.bus]
            register_device(self.state, device.bus, worker.devices[device.name].target)
            care_for(self.config, self.state, worker, devices={device.name})
            self.writers[device.name] = self._writer(device, worker)

    def build(self, names: set[str]) -> None:
        """The workers and write paths of the buses ``names`` (new, or rebuilt), not started."""
        new = self.config
        for bus in new.buses:
            if bus.name in names:
                worker = build_worker(new, bus, self._sinks(), self.state)
                worker.in_use_is_fatal = False  # a port another master holds is retried
                self.workers[bus.name] = worker
        for device in new.devices:
            if device.bus in names:
                self.writers[device.name] = self._writer(device, self.workers[device.bus])

    def _announce_changed(self, changes: ConfigChanges, old: GatewayConfig, mqtt: MqttSink) -> None:
        """MQTT: each changed device announced anew at its next cycle, as it is polled now.

        The points it no longer polls lose their retained values and their Home Assistant
        entities; a device of another profile now loses all of the former's.
        """
        after = {device.name: device for device in self.config.devices}
        for device in old.devices:
            info = self.state.devices.get((device.bus, device.name))
            if device.name not in changes.devices_changed or info is None:
                continue
            now = after[device.name]
            profile = get_profile(info.profile)
            if now.profile != device.profile:
                mqtt.forget(device.bus, device.name, profile, info.intervals)
                continue
            polled = device_target(now, self.config.bus(now.bus)).intervals
            dropped = [point for point in info.intervals if point not in polled]
            mqtt.replan(device.bus, device.name, profile, dropped)

    async def _change_bus(self, name: str, old: GatewayConfig) -> bool:
        """One bus changed in its running worker; what it polls and runs otherwise goes on.

        A new line if its settings changed; the devices added, re-planned and removed.
        False if its line is paused for a scan: nothing changed, the caller rebuilds it.
        """
        new = self.config
        worker = self.workers[name]
        bus = new.bus(name)
        if _line_of(bus) != _line_of(old.bus(name)):
            line = bus_line(new, bus)
            if not await worker.use_line(line):
                return False
            self.state.remove_line(name)
            self.state.add_line(name, line.stats, worker.health)
        worker.reconnect_max_s = bus.reconnect_max_s
        # A device the reload did not change keeps its target as it is, its phase among
        # it (another device on the bus must not shift its slot), unless the bus's own
        # settings give it another (its timeout or retries); the worker tells a re-plan
        # of the same sensor from another sensor.
        unchanged = {device.name for device in old.devices_on(name) if device in new.devices}
        targets = []
        for built in bus_targets(new, bus):
            state = worker.devices.get(built.name)
            kept = state.target if state is not None and built.name in unchanged else None
            same = kept is not None and dataclasses.replace(built, phase=kept.phase) == kept
            targets.append(kept if same and kept is not None else built)
        try:
            async with asyncio.timeout(SHUTDOWN_S):
                await worker.change_devices(targets)
        except TimeoutError:
            _LOGGER.warning(
                "reload: %s takes its new devices after the transaction in flight", name
            )
        return True

    async def _stop_bus(self, name: str) -> None:
        """A bus removed or rebuilt: its worker stops after the frame in flight, its port closes."""
        worker = self.workers.pop(name)
        worker.request_stop()
        task = self._tasks.pop(name, None)
        if task is not None:
            await asyncio.wait([task], timeout=SHUTDOWN_S)
            await stop_tasks([task])
        await worker.line.close()
        self.state.remove_line(name)

    def _forget_device(self, bus: str, name: str, mqtt: MqttSink | None) -> None:
        """A device gone for good: forgotten by the state and by MQTT, its write path gone."""
        info = self.state.devices.get((bus, name))
        self.state.remove_device(bus, name)
        self.writers.pop(name, None)
        if info is not None and mqtt is not None:
            mqtt.forget(bus, name, get_profile(info.profile), info.intervals)


def _line_of(bus: BusConfig) -> tuple[object, ...]:
    """What a bus's line is built from: another value of any takes a new line."""
    return (bus.port, bus.line, bus.echo, bus.rs485, bus.tcp)


def _another_sensor(before: DeviceConfig, after: DeviceConfig) -> bool:
    """Whether a device the reload kept by name is another sensor: moved, readdressed, other."""
    return (
        before.bus != after.bus
        or before.address != after.address
        or before.profile != after.profile
    )
