"""The running gateway: its parts built from a config, supervised, and changed by a reload.

:class:`RunningGateway` holds what one config builds (the bus workers, the write paths, the
sinks, the shared bus, the web page, the metrics server) and applies a reloaded config by
changing only what differs (:class:`~gateway.config.changes.ConfigChanges`): the buses
change in place (:class:`~gateway.app.buses.Buses`: a bus whose settings and devices are
the same keeps its worker, its open port and its schedule, a changed one its worker); a
section whose settings are the same keeps its connection. What must outlive any change
lives here for the whole run: the state, the flash-write ledger, the MQTT queue on disk,
the web page's sessions.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import time
from typing import TYPE_CHECKING, Any, Final, Protocol

from gateway.app.audit import AuditTrail
from gateway.app.build import (
    care_for,
    flash_budgets,
    publish_settings,
    retarget_scans,
    retarget_shared,
    shared_bus_server,
    sparkplug_devices,
    sparkplug_sink,
    state_directory,
    verifiable_points,
    web_page,
    wire_commands,
    wire_feeds,
    wire_sparkplug_commands,
)
from gateway.app.buses import Buses
from gateway.app.logs import configure_logging
from gateway.app.reload import (
    ReloadRequests,
    reload_environment,
    remove_pid_file,
    write_pid_file,
    write_status,
)
from gateway.app.tasks import ended_unasked, stop_tasks
from gateway.config import ConfigProblems, load_config
from gateway.config.changes import ConfigChanges
from gateway.control.flash import LEDGER_FILE, FlashLedger, utc_today
from gateway.errors import ConfigError, GatewayError
from gateway.records.reloads import record_reload
from gateway.shared.host_clock import trust_from_environment
from gateway.shared.state import GatewayState

if TYPE_CHECKING:
    from collections.abc import Coroutine, Sequence
    from pathlib import Path

    from gateway.config import GatewayConfig
    from gateway.control.command_router import CommandRouter
    from gateway.control.feeds import FeedEngine
    from gateway.control.shared_bus import SharedBusServer
    from gateway.control.writes import SafeWriter
    from gateway.line.engine.worker import BusWorker
    from gateway.line.samples import Sink
    from gateway.publish.mqtt import MqttSink
    from gateway.publish.prometheus import MetricsServer
    from gateway.publish.sparkplug import SparkplugSink
    from gateway.web import Sessions, WebServer
    from gateway.web.calibration import Calibrations

_LOGGER = logging.getLogger(__name__)


class RunningGateway:
    """Every part of the gateway that one config builds, and the tasks that run them."""

    def __init__(
        self, config: GatewayConfig, state: GatewayState, sinks: Sequence[Sink] = ()
    ) -> None:
        """Build the parts of ``config``; :meth:`start` starts them. ``sinks``: besides MQTT's."""
        self.config = config
        self.state = state
        state.clock.trust_unsynchronised = _trusted(config)
        self.extra_sinks = list(sinks)
        self.state_dir = state_directory(config)
        self.ledger = FlashLedger(self.state_dir / LEDGER_FILE)
        state.storage.track(self.ledger.health)
        self.mqtt: MqttSink | None = None
        self.audit = AuditTrail(
            self.state_dir,
            state,
            config=lambda: self.config,
            mqtt=lambda: self.mqtt,
            points=verifiable_points(config),
        )
        self.records = self.audit.store
        state.writes.flash_counts = lambda: self.ledger.counts(utc_today())
        state.writes.flash_budgets = flash_budgets(config)
        if config.mqtt.enabled:
            from gateway.publish.mqtt import MqttSink  # noqa: PLC0415 - aiomqtt and paho with it

            self.mqtt = MqttSink(
                config.mqtt,
                state,
                state_dir=self.state_dir,
                publish=publish_settings(config),
                retained_also=self.audit.retained,
            )
        self.sparkplug: SparkplugSink | None = (
            sparkplug_sink(config, state) if config.sparkplug.enabled else None
        )
        self.buses = Buses(
            config, state, self.ledger, self._sinks, records=self.records, feeds=self.audit.feeds
        )
        # The same dictionaries for the whole run: a reload changes them in place.
        self.workers: dict[str, BusWorker] = self.buses.workers
        self.writers: dict[str, SafeWriter] = self.buses.writers
        self.verifier = self.audit.verify_with(self.writers)
        self.feeds: FeedEngine | None = wire_feeds(
            config, state, list(self.workers.values()), self.writers, self.mqtt
        )
        self.router: CommandRouter | None = wire_commands(
            config, state, self.writers, self.mqtt, self.verifier
        )
        self.shared: SharedBusServer | None = shared_bus_server(
            config, list(self.workers.values()), self.ledger, state, self.records
        )
        wire_sparkplug_commands(config, self.writers, self.sparkplug)
        self.page: WebServer | None = web_page(
            config,
            state,
            self.workers,
            self.writers,
            records=self.records,
            verifier=self.verifier,
        )
        self.metrics: MetricsServer | None = None
        self._tasks: dict[str, asyncio.Task[None]] = {}  # the sinks', the feeds', the page's
        # A reload's, while the page is rebuilt.
        self._kept_sessions: Sessions | None = None
        self._kept_calibrations: Calibrations | None = None

    def _sinks(self) -> list[Sink]:
        """What every bus hands its samples to (the state's sink is each worker's own)."""
        return [
            *self.extra_sinks,
            self.audit.recent,
            *([self.mqtt] if self.mqtt is not None else []),
            *([self.sparkplug] if self.sparkplug is not None else []),
        ]

    # --- start and stop ----------------------------------------------------------------

    async def start(self, stack: contextlib.AsyncExitStack) -> None:
        """Claim the ports, then start every part; ``stack`` closes what stays open."""
        stack.callback(self.ledger.close)
        stack.callback(self.audit.close)
        self.audit.start()
        self._start_metrics()
        stack.callback(self._stop_metrics)
        stack.push_async_callback(self.buses.close_lines)
        # The ports first: a port another master holds stops the start here, with the
        # remedy, before the shared bus's listeners or the sinks are up.
        await self.buses.claim_ports()
        if self.shared is not None:
            await self.shared.start()
        stack.push_async_callback(self._close_shared)
        self.buses.start()
        # Unwound first: the workers stop before their ports close, also when a part
        # started after them (the web page on a taken port) fails the start.
        stack.push_async_callback(self.stop)
        self._start_task("mqtt", self.mqtt)
        self._start_task("sparkplug", self.sparkplug)
        self._start_task("feeds", self.feeds)
        self._start_task("records", self.audit)
        if self.page is not None:
            await self._run_page(self.page)

    def tasks(self) -> list[asyncio.Task[None]]:
        """The tasks that run now: a bus's or a sink's ending is the gateway's failure."""
        return [*self.buses.tasks(), *self._tasks.values()]

    async def stop(self) -> None:
        """Stop the buses, then the sinks.

        The buses first, after the frame in flight, so that their last samples still reach
        the sinks; then the sinks (MQTT says offline, the queue stays on disk).
        """
        await self.buses.stop()
        await stop_tasks(list(self._tasks.values()))
        if self.page is not None:
            with contextlib.suppress(Exception):
                await self.page.stop()

    def _start_task(self, key: str, part: _Runs | None) -> None:
        if part is not None:
            self._tasks[key] = asyncio.create_task(part.run(), name=_TASK_NAMES[key])

    async def _stop_task(self, key: str) -> None:
        task = self._tasks.pop(key, None)
        if task is not None:
            await stop_tasks([task])

    def _start_metrics(self) -> None:
        if self.config.prometheus.enabled:
            from gateway.publish.prometheus import MetricsServer  # noqa: PLC0415

            self.metrics = MetricsServer.of(self.state, self.config.prometheus)
            self.metrics.start()

    def _stop_metrics(self) -> None:
        if self.metrics is not None:
            self.metrics.stop()
            self.metrics = None

    async def _close_shared(self) -> None:
        if self.shared is not None:
            await self.shared.close()

    async def _run_page(self, page: WebServer) -> None:
        await page.start()  # a port that is taken stops the start, with the reason
        self._tasks["web"] = asyncio.create_task(page.run(), name=_TASK_NAMES["web"])

    # --- reload ------------------------------------------------------------------------

    async def reload(self, path: Path) -> None:
        """Read, validate and apply the config file once; its outcome in the state and on disk."""
        status = self.state.config
        started = time.monotonic()
        try:
            environ = reload_environment(self.state_dir)
            new: GatewayConfig = await asyncio.get_running_loop().run_in_executor(
                None, lambda: load_config(path, environ=environ)
            )
        except ConfigProblems as exc:
            problems = [str(problem) for problem in exc.problems]
            _LOGGER.error(  # noqa: TRY400 - the problems are the message, not a traceback
                "reload: %s has %d problem(s); the running config stays:\n  %s",
                path,
                len(problems),
                "\n  ".join(problems),
            )
            status.refused(problems)
            record_reload(self.records, path, problems=problems)
        except (ConfigError, OSError, ValueError) as exc:
            _LOGGER.error("reload: cannot read %s (%s); the running config stays", path, exc)  # noqa: TRY400 - the reason is the message
            status.refused([f"{path}: {exc}"])
            record_reload(self.records, path, problems=[f"{path}: {exc}"])
        else:
            try:
                changes = await self.apply(new)
            except GatewayError as exc:  # a listener's port taken, a TLS file gone: said, not fatal
                _LOGGER.error("reload: %s was applied in part: %s", path, exc)  # noqa: TRY400
                status.refused([str(exc)])
                record_reload(self.records, path, problems=[str(exc)], applied="in part")
            else:
                summary = changes.summary()
                _LOGGER.info(
                    "reload: %s applied in %.2f s: %s", path, time.monotonic() - started, summary
                )
                status.reloaded(summary)
                record_reload(self.records, path, summary=summary)
        write_status(self.state_dir, status.reloads, status.last_reload_ok, status.problems)

    async def apply(self, new: GatewayConfig) -> ConfigChanges:
        """Change the running parts to ``new`` (valid already), and only what differs.

        The buses that go stop first, and those that changed change in their running
        workers (a new line if their settings changed; devices added, re-planned and
        removed between two transactions, so what runs on the others, a calibration
        among it, goes on). The devices that go are said offline and their retained
        topics cleared. Then the parts whose section changed stop, the new buses are
        built, the parts that reach devices (write paths, feeds, commands, the shared
        bus, the page's scans, Sparkplug) are pointed at them, and all are started.
        """
        old = self.config
        changes = ConfigChanges.between(old, new)
        for setting in changes.restart_only:
            _LOGGER.warning(
                "reload: %s changes only at a restart (the queue and the ledger live there); "
                "it stays %s until then",
                setting,
                getattr(old, setting),
            )
        if "logging" in changes.sections:
            configure_logging(new.logging)
        self.config = new
        self.state.clock.trust_unsynchronised = _trusted(new)
        self.state.writes.flash_budgets = flash_budgets(new)
        self.audit.watch(verifiable_points(new))
        self.buses.config = new
        rebuilt = await self.buses.change(changes, old, self.mqtt)
        await self._stop_sections(changes, old)
        coming = {*changes.buses_added, *rebuilt}
        self.buses.build(coming)
        if "care" in changes.sections:
            for name, worker in self.workers.items():
                if name not in coming:
                    care_for(new, self.state, worker)
        await self._start_sections(changes)
        self.buses.start()
        return changes

    async def _stop_sections(self, changes: ConfigChanges, old: GatewayConfig) -> None:
        """Stop the parts whose own section changed; the others keep their connections."""
        new, sections = self.config, changes.sections
        if "mqtt" in sections:
            await self._stop_mqtt(new)
        elif self.mqtt is not None:
            self.mqtt.set_publish(publish_settings(new))
        if "prometheus" in sections:
            self._stop_metrics()
            self._start_metrics()
        if "shared_bus" in sections and self.shared is not None:
            await self.shared.close()
            self.shared = None
        self._kept_sessions = self._kept_calibrations = None
        if "web" in sections and self.page is not None:
            # Signed-in operators stay signed in, and their calibrations under way go on
            # (stopped before its task, whose end would otherwise stop them).
            keep = _sign_in(old) == _sign_in(new)
            await self.page.stop(keep_calibrations=keep)
            await self._stop_task("web")
            if keep:
                self._kept_sessions = self.page.sessions
                self._kept_calibrations = self.page.calibrations
            self.page = None

    async def _stop_mqtt(self, new: GatewayConfig) -> None:
        """MQTT's section changed: its session ends (offline said, what is unsent kept on disk)."""
        await self._stop_task("mqtt")
        if self.mqtt is None and new.mqtt.enabled:
            from gateway.publish.mqtt import MqttSink  # noqa: PLC0415 - aiomqtt and paho with it

            self.mqtt = MqttSink(
                new.mqtt,
                self.state,
                state_dir=self.state_dir,
                publish=publish_settings(new),
                retained_also=self.audit.retained,
            )
            for worker in self.workers.values():
                worker.sinks.append(self.mqtt)
        elif self.mqtt is not None and not new.mqtt.enabled:
            for worker in self.workers.values():
                if self.mqtt in worker.sinks:
                    worker.sinks.remove(self.mqtt)
            self.mqtt = None
        elif self.mqtt is not None:
            self.mqtt.reconfigure(new.mqtt, publish_settings(new))

    async def _start_sections(self, changes: ConfigChanges) -> None:
        """Point what reaches devices at the buses now running; start what was rebuilt."""
        new, sections = self.config, changes.sections
        buses_differ = changes.buses_added or changes.buses_removed or changes.buses_changed
        if "mqtt" in sections:
            self._start_task("mqtt", self.mqtt)
        if {"commands", "mqtt"} & sections:
            if self.mqtt is not None and self.router in self.mqtt.listeners:
                self.mqtt.listeners.remove(self.router)
            self.router = wire_commands(new, self.state, self.writers, self.mqtt, self.verifier)
        if {"feeds", "mqtt"} & sections or (buses_differ and (self.feeds or new.feeds)):
            self._rewire_feeds(list(self.workers.values()))
        await self._start_shared(changes)
        await self._start_page(changes)
        if {"sparkplug", "mqtt"} & sections:
            if self.sparkplug is not None or new.sparkplug.enabled:
                await self._restart_sparkplug()
        elif self.sparkplug is not None and buses_differ:
            # The node's own metrics are the same: no new NBIRTH, only the devices' deaths
            # and births (a device that moved bus counts as changed).
            self.sparkplug.change_devices(sparkplug_devices(new), changed=changes.devices_changed)

    async def _start_shared(self, changes: ConfigChanges) -> None:
        """The shared bus anew if its section changed, else its listeners on the new buses."""
        if self.shared is None:
            workers = list(self.workers.values())
            self.shared = shared_bus_server(
                self.config, workers, self.ledger, self.state, self.records
            )
            if self.shared is not None:
                await self.shared.start()
        elif changes.buses_added or changes.buses_removed or changes.buses_changed:
            retarget_shared(self.config, self.shared, self.workers)

    async def _start_page(self, changes: ConfigChanges) -> None:
        """The page anew if its section changed (sessions kept), else its scans retargeted."""
        if "web" in changes.sections:
            self.page = web_page(
                self.config,
                self.state,
                self.workers,
                self.writers,
                sessions=self._kept_sessions,
                calibrations=self._kept_calibrations,
                records=self.records,
                verifier=self.verifier,
            )
            if self.page is not None:
                await self._run_page(self.page)
        elif self.page is not None and self.page.scans is not None:
            retarget_scans(self.config, self.page.scans, self.workers)

    def _rewire_feeds(self, workers: Sequence[BusWorker]) -> None:
        """The feed engine anew (its writers or its sources changed), on every bus and MQTT."""
        old = self.feeds
        if old is not None:
            for worker in workers:
                if old in worker.sinks:
                    worker.sinks.remove(old)
            if self.mqtt is not None and old in self.mqtt.listeners:
                self.mqtt.listeners.remove(old)
        task = self._tasks.pop("feeds", None)
        if task is not None:
            task.cancel()
        self.feeds = wire_feeds(self.config, self.state, workers, self.writers, self.mqtt)
        self._start_task("feeds", self.feeds)

    async def _restart_sparkplug(self) -> None:
        """A new edge node session for the new set of devices: NDEATH, then NBIRTH and DBIRTHs."""
        await self._stop_task("sparkplug")
        old = self.sparkplug
        self.sparkplug = (
            sparkplug_sink(self.config, self.state) if self.config.sparkplug.enabled else None
        )
        for worker in self.workers.values():
            if old is not None and old in worker.sinks:
                worker.sinks.remove(old)
            if self.sparkplug is not None and self.sparkplug not in worker.sinks:
                worker.sinks.append(self.sparkplug)
        wire_sparkplug_commands(self.config, self.writers, self.sparkplug)
        self._start_task("sparkplug", self.sparkplug)


class _Runs(Protocol):
    def run(self) -> Coroutine[Any, Any, None]: ...


_TASK_NAMES: Final = {
    "mqtt": "sink[mqtt]",
    "sparkplug": "sink[sparkplug]",
    "feeds": "feeds",
    "web": "web",
    "records": "records",
}


def _trusted(config: GatewayConfig) -> bool:
    """``clock.trust_unsynchronised``; false in the file leaves the environment's word."""
    return config.clock.trust_unsynchronised or trust_from_environment()


def _sign_in(config: GatewayConfig) -> tuple[object, ...]:
    """What a session was signed in with: the same after a reload keeps the sessions."""
    web = config.web
    return (web.password, web.password_sha256, web.session_minutes, web.users_file)


async def run(
    config: GatewayConfig,
    sinks: Sequence[Sink] = (),
    *,
    stop: asyncio.Event | None = None,
    state: GatewayState | None = None,
    config_path: Path | None = None,
    reloads: ReloadRequests | None = None,
) -> None:
    """Poll every bus and publish until ``stop`` is set (default: SIGINT or SIGTERM).

    MQTT and Prometheus are started from the config (each can be disabled); ``sinks``
    are added to them (the console, tests). With ``config_path``, SIGHUP (or ``reloads``
    asked) reads that file again and applies what changed (:mod:`gateway.app.reload`).
    """
    state = state or GatewayState()
    reloads = reloads or ReloadRequests()
    stop = stop or _stop_on_signals(reloads if config_path is not None else None)
    gateway = RunningGateway(config, state, sinks)
    pid_file = write_pid_file(gateway.state_dir) if config_path is not None else None
    async with contextlib.AsyncExitStack() as stack:
        stack.callback(remove_pid_file, pid_file)
        await gateway.start(stack)
        stopping = asyncio.create_task(stop.wait(), name="gateway.stop")
        asked = asyncio.create_task(reloads.next(), name="gateway.reload")
        try:
            while True:
                done, _ = await asyncio.wait(
                    [stopping, asked, *gateway.tasks()], return_when=asyncio.FIRST_COMPLETED
                )
                if stopping in done:
                    break
                for task in done - {stopping, asked}:
                    raise ended_unasked(task)
                if asked in done:
                    if config_path is not None:
                        await gateway.reload(config_path)
                    asked = asyncio.create_task(reloads.next(), name="gateway.reload")
        finally:
            asked.cancel()
            await stop_tasks([stopping])
    _LOGGER.info("stopped")


def _stop_on_signals(reloads: ReloadRequests | None) -> asyncio.Event:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    loop.add_signal_handler(signal.SIGHUP, reloads.ask if reloads is not None else _not_reloadable)
    return stop


def _not_reloadable() -> None:
    # Without a config file (a config built in code: tests, the demo) there is nothing to read
    # again; SIGHUP must not kill the process.
    _LOGGER.warning("SIGHUP: this gateway was given no config file to reload")
