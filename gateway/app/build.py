"""What a config builds: the bus workers, the write paths, the sinks, the shared bus, the page.

Each builder makes one part from the config and registers it where the gateway's state
needs it; :class:`gateway.app.running.RunningGateway` calls them at the start and again
for what a reload changes. The command line's one-off commands use the same builders
(:func:`device_target`, :func:`state_directory`), so a device is polled the same way
wherever it is read from.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING

from gateway.care.rules import rules_for
from gateway.config import Cadence, PublishSettings
from gateway.control.link import DeviceLink
from gateway.control.ports import port_options
from gateway.control.verification import verifiable_point
from gateway.control.writes import SafeWriter
from gateway.errors import CommandRejectedError
from gateway.line.engine.devices import DeviceTarget
from gateway.line.engine.foreign import SharePolicy
from gateway.line.engine.schedule import spread_phase
from gateway.line.engine.worker import BusWorker
from gateway.line.transports.factory import build_line
from gateway.line.transports.port_names import SystemRoots, port_name_advice
from gateway.profiles.serial_number import pinned_serial
from gateway.records.actor import Actor, Via
from gateway.shared.state import DeviceInfo, GatewayState, StateSink

# What only an optional feature needs (MQTT and its client, Prometheus and its server, the
# commands, the feeds, Sparkplug with protobuf, the shared bus, the web page with aiohttp)
# is imported where that feature is configured, not here: `gateway run` holds in memory,
# for as long as it runs, only the libraries of what its config switches on
# (tests/cli/test_imports.py checks it).
if TYPE_CHECKING:
    from collections.abc import Collection, Iterable, Mapping, Sequence

    from gateway.config import (
        BusConfig,
        DeviceConfig,
        GatewayConfig,
    )
    from gateway.control.command_router import CommandRouter
    from gateway.control.feeds import FeedEngine
    from gateway.control.flash import FlashLedger
    from gateway.control.shared_bus import SharedBusServer
    from gateway.control.verification import Verifier
    from gateway.line.boundary import Line
    from gateway.line.samples import Sink
    from gateway.profiles import Profile
    from gateway.publish.mqtt import MqttSink
    from gateway.publish.sparkplug import SparkplugSink
    from gateway.records import FeedCounts, RecordStore
    from gateway.shared.host_clock import HostClock
    from gateway.web import LineScans, Sessions, WebServer
    from gateway.web.calibration import Calibrations

_LOGGER = logging.getLogger(__name__)


def device_target(
    device: DeviceConfig, bus: BusConfig, *, phase: float | None = None
) -> DeviceTarget:
    """What the bus engine polls for one configured device.

    ``phase``: the spread the gateway gives it (:func:`spread_phase`), which its own
    ``poll_phase`` overrides; ``None`` and no ``poll_phase``: deadlines from each start.
    """
    profile = device.get_profile()
    intervals: dict[str, float | None] = {}
    for point in profile.points:
        if point.view:
            continue
        schedule = device.interval_for(point)
        if schedule.cadence is Cadence.PERIODIC:
            intervals[point.name] = schedule.interval_s
        elif schedule.cadence is Cadence.ON_CONNECT:
            intervals[point.name] = None
    return DeviceTarget(
        name=device.name,
        address=device.address,
        profile=profile,
        intervals=intervals,
        float_order=device.float_order,
        timeout_s=device.response_timeout(bus),
        min_response_time_s=device.min_response_time_ms / 1000,
        extra_gap_s=device.inter_frame_gap_ms / 1000,
        retries=device.retries_on(bus),
        offline_after=device.offline_after,
        serial_number=pinned_serial(profile, device.serial_number),
        phase=device.poll_phase if device.poll_phase is not None else phase,
    )


def build_workers(
    config: GatewayConfig, sinks: Sequence[Sink], state: GatewayState | None = None
) -> list[BusWorker]:
    """One worker per configured bus, with its devices; registered in ``state`` if given."""
    return [build_worker(config, bus, sinks, state) for bus in config.buses]


def build_worker(
    config: GatewayConfig, bus: BusConfig, sinks: Sequence[Sink], state: GatewayState | None
) -> BusWorker:
    """The worker of one configured bus, with its devices; registered in ``state`` if given."""
    targets = bus_targets(config, bus)
    worker = BusWorker(
        name=bus.name,
        line=bus_line(config, bus),
        devices=targets,
        sinks=[StateSink(state), *sinks] if state is not None else sinks,
        reconnect_max_s=bus.reconnect_max_s,
    )
    if state is not None:
        state.add_line(bus.name, worker.line.stats, worker.health)
        for target in targets:
            register_device(state, bus.name, target)
        care_for(config, state, worker)
    return worker


def bus_targets(config: GatewayConfig, bus: BusConfig) -> list[DeviceTarget]:
    """What the worker of ``bus`` polls: its devices, each at its share of the interval."""
    b = next(i for i, each in enumerate(config.buses) if each.name == bus.name)
    on_bus = config.devices_on(bus.name)
    # Spread across the interval and across buses: not 256 cycles due at one instant.
    phases = (
        spread_phase(device=j, devices=len(on_bus), bus=b, buses=len(config.buses))
        for j in range(len(on_bus))
    )
    return [device_target(d, bus, phase=p) for d, p in zip(on_bus, phases, strict=True)]


def bus_line(config: GatewayConfig, bus: BusConfig) -> Line:
    """The line of a configured bus, not open yet."""
    if (advice := port_name_advice(bus.port, SystemRoots())) is not None:
        _LOGGER.warning("%s: %s", bus.name, advice)  # as check-config warns
    return build_line(
        port=bus.port,
        line=bus.line,
        tcp=bus.tcp,
        bus=bus.name,
        echo=bus.echo,
        options=port_options(bus, config.shared_bus),
    )


def register_device(state: GatewayState, bus: str, target: DeviceTarget) -> None:
    """A device of a running bus, as the state shows it (the metrics, the page, MQTT)."""
    state.add_device(
        DeviceInfo(
            bus=bus,
            name=target.name,
            profile=target.profile.id,
            address=target.address,
            intervals=target.intervals,  # shared, not copied: read-only
        )
    )


def care_for(
    config: GatewayConfig,
    state: GatewayState,
    worker: BusWorker,
    devices: Collection[str] | None = None,
) -> None:
    """Sensor care's rules for the devices of ``worker`` (or those of them named)."""
    for device in config.devices_on(worker.name):
        if devices is not None and device.name not in devices:
            continue
        target = worker.devices[device.name].target
        state.care.add_device(
            bus=worker.name,
            device=target.name,
            profile=target.profile,
            rules=rules_for(config, device),
            polled=target.intervals,
        )


def build_writer(
    device: DeviceConfig,
    worker: BusWorker,
    ledger: FlashLedger,
    clock: HostClock | None = None,
    *,
    records: RecordStore | None = None,
    feeds: FeedCounts | None = None,
) -> SafeWriter:
    """The write path of one configured device: flash policy, host clock, the records."""
    return SafeWriter(
        DeviceLink(worker, device.name),
        policy=device.flash_policy(),
        ledger=ledger,
        clock=clock,
        records=records,
        feeds=feeds,
    )


def build_writers(
    config: GatewayConfig,
    workers: Sequence[BusWorker],
    ledger: FlashLedger,
    clock: HostClock | None = None,
) -> dict[str, SafeWriter]:
    """The write path of every configured device, with its flash policy."""
    by_bus = {worker.name: worker for worker in workers}
    return {
        device.name: build_writer(device, by_bus[device.bus], ledger, clock)
        for device in config.devices
    }


def flash_budgets(config: GatewayConfig) -> dict[tuple[str, str], int]:
    """Each flash-written point's daily budget, by ``(device, point)``, for the metrics."""
    return {
        (device.name, point): device.flash_write_budget
        for device in config.devices
        for point in device.flash_writes
    }


def wire_feeds(
    config: GatewayConfig,
    state: GatewayState,
    workers: Sequence[BusWorker],
    writers: Mapping[str, SafeWriter],
    mqtt: MqttSink | None,
) -> FeedEngine | None:
    """The compensation feeds, if any: a sink of every bus, and MQTT's listener of sources."""
    if not config.feeds:
        return None
    from gateway.control.feeds import FeedEngine  # noqa: PLC0415 - only when configured

    feeds = FeedEngine(config.feeds, writers, state=state)
    for worker in workers:
        worker.sinks.append(feeds)
    if mqtt is not None and feeds.subscriptions():
        mqtt.listeners.append(feeds)
    return feeds


def verifiable_points(config: GatewayConfig) -> dict[str, str]:
    """Each device's point a grab-sample verification compares (its process value)."""
    points = {}
    for device in config.devices:
        try:
            points[device.name] = verifiable_point(device.get_profile()).name
        except CommandRejectedError:
            continue  # a profile without a measured process value: nothing to verify
    return points


def wire_commands(
    config: GatewayConfig,
    state: GatewayState,
    writers: Mapping[str, SafeWriter],
    mqtt: MqttSink | None,
    verifier: Verifier | None = None,
) -> CommandRouter | None:
    """MQTT's ``…/set`` and ``…/command/…`` through the devices' write paths, if commands are on."""
    if mqtt is None or not config.commands.enabled:
        return None
    # The router brings the sensor operations' catalogue: only with commands on.
    from gateway.control.command_router import CommandRouter  # noqa: PLC0415

    actor = Actor(
        user=config.mqtt.username or "mqtt",
        via=Via.MQTT,
        detail=f"client id {mqtt.client_id}",
    )
    router = CommandRouter(
        config.mqtt.base_topic,
        writers,
        state=state,
        qos=config.mqtt.qos,
        actor=actor,
        verifier=verifier,
    )
    mqtt.listeners.append(router)
    return router


def shared_bus_server(
    config: GatewayConfig,
    workers: Sequence[BusWorker],
    ledger: FlashLedger,
    state: GatewayState,
    records: RecordStore | None = None,
) -> SharedBusServer | None:
    """Other masters on the buses (``shared_bus:``), if configured; their share opened."""
    shared = config.shared_bus
    if not shared.enabled:
        return None
    # The listeners, the PDU decoding and pymodbus's TCP framer: only with the bus shared.
    from gateway.control.shared_bus import SharedBusServer, units  # noqa: PLC0415

    open_share(config, workers)
    return SharedBusServer(
        shared,
        units=units(config),
        workers={worker.name: worker for worker in workers},
        ledger=ledger,
        flash_budgets=_flash_budgets_by_device(config),
        state=state,
        clock=state.clock,
        records=records,
    )


def open_share(config: GatewayConfig, workers: Iterable[BusWorker]) -> None:
    """Open the buses to other masters' requests, within the configured share."""
    shared = config.shared_bus
    policy = SharePolicy(
        share=shared.bus_share, max_wait_s=shared.max_wait, max_pending=shared.max_pending
    )
    caching = any(client.cache_max_age is not None for client in shared.clients)
    for worker in workers:
        worker.foreign.open(policy)
        worker.transactions.cache.enabled = caching


def retarget_shared(
    config: GatewayConfig, server: SharedBusServer, workers: Mapping[str, BusWorker]
) -> None:
    """After a reload that changed buses: the listeners stay, requests reach the new workers."""
    from gateway.control.shared_bus import units  # noqa: PLC0415 - loaded with the server

    open_share(config, (w for w in workers.values() if w.name not in server.bridge.workers))
    server.bridge.units = units(config)
    server.bridge.workers = dict(workers)
    server.bridge.flash_budgets = _flash_budgets_by_device(config)
    buses = server.status.buses
    for name in [name for name in buses if name not in workers]:
        del buses[name]
    for name, worker in workers.items():
        buses[name] = worker.foreign.stats


def _flash_budgets_by_device(config: GatewayConfig) -> dict[str, int]:
    return {device.name: device.flash_write_budget for device in config.devices}


def sparkplug_sink(config: GatewayConfig, state: GatewayState) -> SparkplugSink:
    """The Sparkplug B edge node of every configured device (the points each polls)."""
    # Sparkplug's payloads are protobuf messages: protobuf only with Sparkplug on.
    from gateway.publish.sparkplug import SparkplugSink  # noqa: PLC0415

    return SparkplugSink(
        config.sparkplug,
        config.mqtt,
        sparkplug_devices(config),
        state_dir=state_directory(config),
        state=state,
    )


def sparkplug_devices(config: GatewayConfig) -> list[tuple[str, Profile, Collection[str]]]:
    """Each configured device as the edge node reports it: name, profile, points polled."""
    return [
        (target.name, target.profile, target.intervals.keys())
        for bus in config.buses
        for target in (device_target(d, bus) for d in config.devices_on(bus.name))
    ]


def wire_sparkplug_commands(
    config: GatewayConfig, writers: dict[str, SafeWriter], sparkplug: SparkplugSink | None
) -> None:
    """DCMD writes through each device's safe write path (unless commands are off).

    The same writers as MQTT's commands and the feeds: one write path per device.
    """
    if sparkplug is not None and config.commands.enabled:
        from gateway.control.sparkplug_commands import SparkplugCommands  # noqa: PLC0415

        actor = Actor(
            user=config.mqtt.username or "sparkplug",
            via=Via.SPARKPLUG,
            detail=f"client id {sparkplug.session.client_id}; DCMD",
        )
        sparkplug.session.commands = SparkplugCommands(sparkplug, writers, actor=actor)


def web_page(
    config: GatewayConfig,
    state: GatewayState,
    workers: Mapping[str, BusWorker],
    writers: Mapping[str, SafeWriter],
    *,
    sessions: Sessions | None = None,
    calibrations: Calibrations | None = None,
    records: RecordStore | None = None,
    verifier: Verifier | None = None,
) -> WebServer | None:
    """The commissioning and calibration page, if ``web.enabled``.

    ``sessions`` and ``calibrations``: a former page's, kept by a reload. ``records`` and
    ``verifier``: the run's record store (the page's records view) and its grab-sample
    verifications (the page's form).
    """
    if not config.web.enabled:
        return None
    # Here, not at the top: without the page, `gateway run` holds neither aiohttp nor the
    # calibrations and the scan in memory (tests/cli/test_imports.py checks it).
    from gateway.web import LineScans, WebServer  # noqa: PLC0415
    from gateway.web.users import UserBook, users_path  # noqa: PLC0415

    scans = LineScans(list(workers.values()), {})
    retarget_scans(config, scans, workers)
    return WebServer(
        config.web,
        state,
        writers,
        scans=scans,
        sessions=sessions,
        calibrations=calibrations,
        users=UserBook(users_path(config.web, state_directory(config))),
        records=records,
        verifier=verifier,
    )


def retarget_scans(
    config: GatewayConfig, scans: LineScans, workers: Mapping[str, BusWorker]
) -> None:
    """The page's scans on the running buses, each in its configured format and port options."""
    scans.retarget(
        workers,
        formats={bus.name: bus.line for bus in config.buses},
        options={bus.name: port_options(bus, config.shared_bus) for bus in config.buses},
    )


def state_directory(config: GatewayConfig | None) -> Path:
    """Where state that must survive a restart lives: config, systemd's, or ./state.

    ``None``: a config that cannot be read (``gateway reload`` still finds the service's).
    """
    if config is not None and config.state_dir is not None:
        return config.state_dir
    if systemd := os.environ.get("STATE_DIRECTORY"):
        return Path(systemd.split(":")[0])
    return Path("state")


def publish_settings(config: GatewayConfig) -> dict[tuple[str, str], PublishSettings]:
    """The publish mode of every point whose mode is not the default: its own, else its device's.

    A point without an entry is published on every poll (``PublishSettings()``); at 16
    buses of 16 sensors an entry for each of some 26,000 points cost megabytes.
    """
    default = PublishSettings()
    result = {}
    for device in config.devices:
        for point in device.get_profile().points:
            own = device.points.get(point.name)
            chosen = own.publish if own is not None and own.publish is not None else device.publish
            if chosen != default:
                result[device.name, point.name] = chosen
    return result
