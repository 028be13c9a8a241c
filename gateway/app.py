"""The running gateway: one task per bus under one supervisor, and the sinks they feed."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import signal
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

from gateway.care.rules import rules_for
from gateway.config import Cadence, PublishSettings
from gateway.control.flash import LEDGER_FILE, FlashLedger, utc_today
from gateway.control.link import DeviceLink
from gateway.control.writes import SafeWriter
from gateway.line.devices import DeviceTarget
from gateway.line.factory import build_line
from gateway.line.foreign import SharePolicy
from gateway.line.port_access import SystemRoots, port_name_advice, port_options
from gateway.line.schedule import spread_phase
from gateway.line.worker import BusWorker
from gateway.profiles.identity import pinned_serial
from gateway.publish.state import DeviceInfo, GatewayState, StateSink

# What only an optional feature needs (MQTT and its client, Prometheus and its server, the
# commands, the feeds, Sparkplug with protobuf, the shared bus, the web page with aiohttp)
# is imported where that feature is configured, not here: `gateway run` holds in memory,
# for as long as it runs, only the libraries of what its config switches on
# (tests/test_imports.py checks it).
if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.config import (
        BusConfig,
        DeviceConfig,
        GatewayConfig,
        LoggingConfig,
    )
    from gateway.control.feeds import FeedEngine
    from gateway.control.shared_bus import SharedBusServer
    from gateway.line.samples import Sink
    from gateway.publish.mqtt import MqttSink
    from gateway.publish.prometheus import MetricsServer
    from gateway.publish.sparkplug import SparkplugSink
    from gateway.web import WebServer

_LOGGER = logging.getLogger(__name__)
SHUTDOWN_S = 5.0  # bound on stopping: finish the frame in flight, close the ports


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
    workers = []
    for b, bus in enumerate(config.buses):
        if (advice := port_name_advice(bus.port, SystemRoots())) is not None:
            _LOGGER.warning("%s: %s", bus.name, advice)  # as check-config warns
        on_bus = config.devices_on(bus.name)
        # Spread across the interval and across buses: not 256 cycles due at one instant.
        phases = (
            spread_phase(device=j, devices=len(on_bus), bus=b, buses=len(config.buses))
            for j in range(len(on_bus))
        )
        targets = [device_target(d, bus, phase=p) for d, p in zip(on_bus, phases, strict=True)]
        worker = BusWorker(
            name=bus.name,
            line=build_line(
                port=bus.port,
                line=bus.line,
                tcp=bus.tcp,
                bus=bus.name,
                echo=bus.echo,
                options=port_options(bus, config.shared_bus),
            ),
            devices=targets,
            sinks=[StateSink(state), *sinks] if state is not None else sinks,
            reconnect_max_s=bus.reconnect_max_s,
        )
        if state is not None:
            state.add_line(bus.name, worker.line.stats, worker.health)
            for device, target in zip(on_bus, targets, strict=True):
                state.care.add_device(
                    bus=bus.name,
                    device=target.name,
                    profile=target.profile,
                    rules=rules_for(config, device),
                    polled=target.intervals,
                )
                state.add_device(
                    DeviceInfo(
                        bus=bus.name,
                        name=target.name,
                        profile=target.profile.id,
                        address=target.address,
                        intervals=target.intervals,  # shared, not copied: read-only
                    )
                )
        workers.append(worker)
    return workers


def build_writers(
    config: GatewayConfig, workers: Sequence[BusWorker], ledger: FlashLedger
) -> dict[str, SafeWriter]:
    """The write path of every configured device, with its flash policy."""
    by_bus = {worker.name: worker for worker in workers}
    return {
        device.name: SafeWriter(
            DeviceLink(by_bus[device.bus], device.name),
            policy=device.flash_policy(),
            ledger=ledger,
        )
        for device in config.devices
    }


def _wire_writes(
    config: GatewayConfig,
    state: GatewayState,
    workers: Sequence[BusWorker],
    *,
    writers: dict[str, SafeWriter],
    ledger: FlashLedger,
    mqtt: MqttSink | None,
) -> FeedEngine | None:
    """Commands over MQTT, feeds and the flash-write metrics; the feed engine if any."""
    state.writes.flash_counts = lambda: ledger.counts(utc_today())
    state.writes.flash_budgets = {
        (device.name, point): device.flash_write_budget
        for device in config.devices
        for point in device.flash_writes
    }
    feeds: FeedEngine | None = None
    if config.feeds:
        from gateway.control.feeds import FeedEngine  # noqa: PLC0415 - only when configured

        feeds = FeedEngine(config.feeds, writers, state=state)
        for worker in workers:
            worker.sinks.append(feeds)
    if mqtt is not None and config.commands.enabled:
        # The router brings the sensor operations' catalogue: only with commands on.
        from gateway.control.command_router import CommandRouter  # noqa: PLC0415

        mqtt.listeners.append(
            CommandRouter(config.mqtt.base_topic, writers, state=state, qos=config.mqtt.qos)
        )
    if mqtt is not None and feeds is not None and feeds.subscriptions():
        mqtt.listeners.append(feeds)
    return feeds


def shared_bus_server(
    config: GatewayConfig, workers: Sequence[BusWorker], ledger: FlashLedger, state: GatewayState
) -> SharedBusServer | None:
    """Other masters on the buses (``shared_bus:``), if configured; their share opened."""
    shared = config.shared_bus
    if not shared.enabled:
        return None
    # The listeners, the PDU decoding and pymodbus's TCP framer: only with the bus shared.
    from gateway.control.shared_bus import SharedBusServer, units  # noqa: PLC0415

    policy = SharePolicy(
        share=shared.bus_share, max_wait_s=shared.max_wait, max_pending=shared.max_pending
    )
    caching = any(client.cache_max_age is not None for client in shared.clients)
    for worker in workers:
        worker.foreign.open(policy)
        worker.transactions.cache.enabled = caching
    return SharedBusServer(
        shared,
        units=units(config),
        workers={worker.name: worker for worker in workers},
        ledger=ledger,
        flash_budgets={device.name: device.flash_write_budget for device in config.devices},
        state=state,
    )


def sparkplug_sink(config: GatewayConfig, state: GatewayState) -> SparkplugSink:
    """The Sparkplug B edge node of every configured device (the points each polls)."""
    # Sparkplug's payloads are protobuf messages: protobuf only with Sparkplug on.
    from gateway.publish.sparkplug import SparkplugSink  # noqa: PLC0415

    devices = [
        (target.name, target.profile, target.intervals.keys())
        for bus in config.buses
        for target in (device_target(d, bus) for d in config.devices_on(bus.name))
    ]
    return SparkplugSink(
        config.sparkplug,
        config.mqtt,
        devices,
        state_dir=state_directory(config),
        state=state,
    )


def _wire_sparkplug_commands(
    config: GatewayConfig, writers: dict[str, SafeWriter], sparkplug: SparkplugSink | None
) -> None:
    """DCMD writes through each device's safe write path (unless commands are off).

    The same writers as MQTT's commands and the feeds: one write path per device.
    """
    if sparkplug is not None and config.commands.enabled:
        from gateway.control.sparkplug_commands import SparkplugCommands  # noqa: PLC0415

        sparkplug.session.commands = SparkplugCommands(sparkplug, writers)


def _web_page(
    config: GatewayConfig,
    state: GatewayState,
    workers: Sequence[BusWorker],
    writers: dict[str, SafeWriter],
) -> WebServer | None:
    """The commissioning and calibration page, if ``web.enabled``."""
    if not config.web.enabled:
        return None
    # Here, not at the top: without the page, `gateway run` holds neither aiohttp nor the
    # calibrations and the scan in memory (tests/test_imports.py checks it).
    from gateway.web import LineScans, WebServer  # noqa: PLC0415

    formats = {bus.name: bus.line for bus in config.buses}
    options = {bus.name: port_options(bus, config.shared_bus) for bus in config.buses}
    return WebServer(
        config.web,
        state,
        writers,
        scans=LineScans(workers, formats, options=options),
    )


async def _start_sinks(
    mqtt: MqttSink | None,
    sparkplug: SparkplugSink | None,
    feeds: FeedEngine | None,
    page: WebServer | None,
) -> list[asyncio.Task[None]]:
    """The tasks of MQTT, Sparkplug, the feeds and the web page, named."""
    tasks = [asyncio.create_task(mqtt.run(), name="sink[mqtt]")] if mqtt else []
    if sparkplug is not None:
        tasks.append(asyncio.create_task(sparkplug.run(), name="sink[sparkplug]"))
    if feeds is not None:
        tasks.append(asyncio.create_task(feeds.run(), name="feeds"))
    if page is not None:
        await page.start()  # a port that is taken stops the start, with the reason
        tasks.append(asyncio.create_task(page.run(), name="web"))
    return tasks


def _stop_on_signals() -> asyncio.Event:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    loop.add_signal_handler(signal.SIGHUP, _sighup)
    return stop


def _sighup() -> None:
    # Reloading is not supported: a restart applies a new config in a few seconds and
    # keeps the state (queue, counters) on disk. SIGHUP must not kill the service.
    _LOGGER.warning("SIGHUP: the config is not reloaded; restart the service to apply changes")


def state_directory(config: GatewayConfig) -> Path:
    """Where state that must survive a restart lives: config, systemd's, or ./state."""
    if config.state_dir is not None:
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


async def run(
    config: GatewayConfig,
    sinks: Sequence[Sink] = (),
    *,
    stop: asyncio.Event | None = None,
    state: GatewayState | None = None,
) -> None:
    """Poll every bus and publish until ``stop`` is set (default: SIGINT or SIGTERM).

    MQTT and Prometheus are started from the config (each can be disabled); ``sinks``
    are added to them (the console, tests).
    """
    state = state or GatewayState()
    stop = stop or _stop_on_signals()
    all_sinks: list[Sink] = list(sinks)
    mqtt: MqttSink | None = None
    if config.mqtt.enabled:
        from gateway.publish.mqtt import MqttSink  # noqa: PLC0415 - aiomqtt and paho with it

        mqtt = MqttSink(
            config.mqtt, state, state_dir=state_directory(config), publish=publish_settings(config)
        )
        all_sinks.append(mqtt)
    sparkplug = sparkplug_sink(config, state) if config.sparkplug.enabled else None
    all_sinks.extend([sparkplug] if sparkplug is not None else [])
    ledger = FlashLedger(state_directory(config) / LEDGER_FILE)
    workers = build_workers(config, all_sinks, state)
    writers = build_writers(config, workers, ledger)
    feeds = _wire_writes(config, state, workers, writers=writers, ledger=ledger, mqtt=mqtt)
    shared = shared_bus_server(config, workers, ledger, state)
    _wire_sparkplug_commands(config, writers, sparkplug)
    page = _web_page(config, state, workers, writers)
    metrics: MetricsServer | None = None
    if config.prometheus.enabled:
        from gateway.publish.prometheus import MetricsServer  # noqa: PLC0415

        metrics = MetricsServer.of(state, config.prometheus)
        metrics.start()
    async with contextlib.AsyncExitStack() as stack:
        stack.callback(ledger.close)
        if metrics is not None:
            stack.callback(metrics.stop)
        for worker in workers:
            stack.push_async_callback(worker.line.close)
        # The ports first: a port another master holds stops the start here, with the
        # remedy, before the shared bus's listeners or the sinks are up.
        for worker in workers:
            await worker.claim_port()
        await stack.enter_async_context(shared or contextlib.nullcontext())
        bus_tasks = [asyncio.create_task(w.run(), name=f"bus[{w.name}]") for w in workers]
        sink_tasks = await _start_sinks(mqtt, sparkplug, feeds, page)
        waiter = asyncio.create_task(stop.wait(), name="gateway.stop")
        try:
            done, _ = await asyncio.wait(
                [waiter, *bus_tasks, *sink_tasks], return_when=asyncio.FIRST_COMPLETED
            )
            for task in done:
                if task is not waiter and task.exception() is not None:
                    raise task.exception()  # type: ignore[misc]
        finally:
            # The buses stop first, after the frame in flight, so their last samples still
            # reach the sinks; then the sinks (MQTT says offline, the queue stays on disk).
            for worker in workers:
                worker.request_stop()
            await asyncio.wait(bus_tasks, timeout=SHUTDOWN_S)
            for group in (bus_tasks, [*sink_tasks, waiter]):
                await _stop_tasks(group)
    _LOGGER.info("stopped")


async def _stop_tasks(tasks: Sequence[asyncio.Task[object]]) -> None:
    """Cancel and wait, but never for longer than ``SHUTDOWN_S``: stopping must not hang."""
    if not tasks:
        return
    for task in tasks:
        task.cancel()
    done, pending = await asyncio.wait(tasks, timeout=SHUTDOWN_S)
    for task in pending:
        _LOGGER.warning("%s did not stop within %.0f s; leaving it", task.get_name(), SHUTDOWN_S)
    for task in done:
        if not task.cancelled() and (exc := task.exception()) is not None:
            _LOGGER.debug("%s ended with %r", task.get_name(), exc)


class JsonFormatter(logging.Formatter):
    """One JSON object per line, for journald and container logs."""

    def format(self, record: logging.LogRecord) -> str:
        """The record as ``{"time", "level", "logger", "message"}`` (and the exception)."""
        data = {
            "time": datetime.fromtimestamp(record.created, tz=UTC).isoformat(),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        if record.exc_info:
            data["exception"] = self.formatException(record.exc_info)
        return json.dumps(data, ensure_ascii=False)


def configure_logging(settings: LoggingConfig) -> None:
    """Plain text for a terminal, JSON lines for journald and containers."""
    handler = logging.StreamHandler()
    if settings.format == "json":
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(settings.level)
