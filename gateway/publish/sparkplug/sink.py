"""The Sparkplug sink: poll cycles and availability become the edge node's messages.

:class:`SparkplugSink` is what the bus tasks and the app see. It owns the catalogue of
metrics (:mod:`~gateway.publish.sparkplug.catalogue`), the reporter that remembers what the
host was told (:mod:`~gateway.publish.sparkplug.reports`) and the session with the broker
(:mod:`~gateway.publish.sparkplug.session`), and joins them: a cycle is handed to the
session without waiting, a device going offline is a DDEATH (and dead until it is online
again), its first cycle with an answer after that a DBIRTH. The care metrics (group
``care``) come from the state's care book, which the state's sink fills before this one
sees the cycle.
"""

from __future__ import annotations

import json
import socket
from datetime import UTC, datetime
from typing import TYPE_CHECKING

from gateway.publish.sparkplug import payloads
from gateway.publish.sparkplug.catalogue import FIRST_DEVICE_ALIAS, Catalogue
from gateway.publish.sparkplug.identity import GatewayIdentity
from gateway.publish.sparkplug.readings import Reported
from gateway.publish.sparkplug.reports import Reporter
from gateway.publish.sparkplug.session import SparkplugSession
from gateway.publish.sparkplug.topics import SparkplugTopics
from gateway.publish.store import MessageStore
from gateway.wire.codec import EnumValue

if TYPE_CHECKING:
    from collections.abc import Collection, Iterable, Sequence
    from pathlib import Path

    from gateway.config import MqttConfig, SparkplugConfig
    from gateway.line.samples import DeviceEvent, Sample
    from gateway.profiles.model import Profile
    from gateway.publish.message import Message
    from gateway.publish.sparkplug.catalogue import MetricSpec
    from gateway.shared.state import GatewayState
    from gateway.wire.codec import Decoded

QUEUE_FILE = "sparkplug-queue.sqlite"
BD_SEQ_FILE = "sparkplug-bdseq"
REJECTED_KIND = "sparkplug"  # gateway_writes{kind="sparkplug", outcome="rejected"}


class SparkplugSink:
    """Publishes samples and availability as Sparkplug B; keeps the edge node's session."""

    def __init__(
        self,
        settings: SparkplugConfig,
        broker: MqttConfig,
        devices: Iterable[tuple[str, Profile, Collection[str]]],
        *,
        state_dir: Path,
        state: GatewayState | None = None,
    ) -> None:
        """The metrics of ``devices`` (name, profile, points polled) on ``broker``."""
        self.settings = settings
        self.state = state
        edge = settings.edge_node_id or socket.gethostname().split(".")[0]
        self.topics = SparkplugTopics(settings.group_id, edge, settings.primary_host_id)
        self.catalogue = _catalogue(settings, devices)
        self.reporter = Reporter(
            self.catalogue,
            self.topics,
            birth_wait_s=settings.birth_wait_s,
            care=state.care if state is not None else None,
        )
        store = MessageStore(state_dir / QUEUE_FILE, max_messages=settings.queue_max)
        if state is not None:
            state.storage.track(store.health)
        self.session = SparkplugSession(
            broker,
            settings,
            self.topics,
            store,
            births=self,
            client_id=settings.client_id or f"spb-{settings.group_id}-{edge}",
            bd_seq_path=state_dir / BD_SEQ_FILE,
            on_rejected=self.count_rejected,
            status=state.sparkplug if state is not None else None,
            # One identity per gateway: the MQTT connection's owner claim decides.
            identity=GatewayIdentity(state.mqtt) if state is not None else None,
        )

    # --- the sink -------------------------------------------------------------------

    async def publish(self, samples: Sequence[Sample]) -> None:
        """One device's poll cycle: its DBIRTH, or a DDATA of what changed."""
        if not samples:
            return
        live = self.session.live
        self.session.enqueue(self.reporter.cycle(samples, live=live, now_ms=_now_ms()))

    async def device_event(self, event: DeviceEvent) -> None:
        """Offline: the device's DDEATH; online: its next cycle with an answer births it."""
        if event.online:
            self.reporter.alive(event.device)
            return
        message = self.reporter.ddeath(event.device, _now_ms())
        if message is not None:
            self.session.enqueue([message])

    def change_devices(
        self, devices: Iterable[tuple[str, Profile, Collection[str]]], *, changed: Collection[str]
    ) -> None:
        """A reload's devices, the node's own settings the same: no new NBIRTH.

        A device that went or ``changed`` gets its DDEATH (if it was born) and its metrics
        go; one added or changed gets metrics with aliases the node never gave, and its
        DBIRTH once it answers, as at a start (Sparkplug 3.0: a DBIRTH may follow the
        NBIRTH at any time; a device's metrics change only with a new DBIRTH).
        """
        wanted = {name: (name, profile, polled) for name, profile, polled in devices}
        now = _now_ms()
        deaths = []
        for name in list(self.catalogue.devices):
            if name not in wanted or name in changed:
                message = self.reporter.forget(name, now)
                if message is not None:
                    deaths.append(message)
                del self.catalogue.devices[name]
        fresh = [spec for name, spec in wanted.items() if name not in self.catalogue.devices]
        added = _catalogue(self.settings, fresh, first_alias=self.catalogue.next_alias)
        merged = {**self.catalogue.devices, **added.devices}
        self.catalogue.devices = {name: merged[name] for name in wanted}  # the config's order
        self.catalogue.next_alias = added.next_alias
        self.reporter.track(added.devices)
        if deaths:
            self.session.enqueue(deaths)

    async def run(self) -> None:
        """Keep the session, until cancelled (see :meth:`SparkplugSession.run`)."""
        await self.session.run()

    # --- what the session asks ------------------------------------------------------

    def births(self, bd_seq: int, now_ms: int) -> list[Message]:
        """NBIRTH and the DBIRTH of every device born."""
        return self.reporter.births(bd_seq, now_ms)

    def born_devices(self) -> set[str]:
        """The devices born."""
        return set(self.reporter.born)

    # --- what the commands report ---------------------------------------------------

    def count_rejected(self, device: str) -> None:
        """A refused NCMD or DCMD, in ``gateway_writes`` (kind ``sparkplug``)."""
        if self.state is not None:
            known = device in self.catalogue.devices or device == self.topics.edge
            self.state.count_write(device if known else "unknown", REJECTED_KIND, "rejected")

    def count_outcome(self, device: str, outcome: str) -> None:
        """A DCMD write's outcome (ok, unchanged, failed), in ``gateway_writes``."""
        if self.state is not None:
            self.state.count_write(device, REJECTED_KIND, outcome)

    def report_write(
        self, device: str, spec: MetricSpec, value: Decoded | None, result: dict[str, object]
    ) -> None:
        """The outcome of a DCMD write: the value read back and ``Write/Result`` in a DDATA.

        Sent whatever the deadband: the host sees what the device now holds.
        """
        metrics = self.catalogue.devices[device]
        now = _now_ms()
        changed = []
        if spec.point is not None and value is not None and device in self.reporter.born:
            point_spec = metrics.of_point[spec.point.name]
            scalar = payloads.scalar_of(value, point_spec.datatype)  # type: ignore[arg-type]
            if scalar is not None:
                before = self.reporter.last(device).get(point_spec.alias)
                unit = before.unit if before is not None else point_spec.unit
                reported = Reported(scalar, payloads.QUALITY_GOOD, now, None, unit)
                changed.append(self.reporter.record(device, point_spec, reported))
            label = metrics.label_of.get(spec.point.name)
            if label is not None and isinstance(value, EnumValue):
                reported = Reported(value.label, payloads.QUALITY_GOOD, now)
                changed.append(self.reporter.record(device, label, reported))
        if metrics.result is not None and device in self.reporter.born:
            text = json.dumps(result, ensure_ascii=False, default=str)
            reported = Reported(text, payloads.QUALITY_GOOD, now)
            changed.append(self.reporter.record(device, metrics.result, reported))
        if changed:
            live = self.session.live
            self.session.enqueue(
                [self.reporter.ddata(device, changed, historical=not live, now_ms=now)]
            )


def _catalogue(
    settings: SparkplugConfig,
    devices: Iterable[tuple[str, Profile, Collection[str]]],
    *,
    first_alias: int = FIRST_DEVICE_ALIAS,
) -> Catalogue:
    """The metrics of ``devices`` under the node's groups and deadbands."""
    return Catalogue.build(
        devices,
        deadband=settings.deadband,
        deadbands=settings.deadbands,
        groups=settings.groups,
        device_groups=settings.device_groups,
        first_alias=first_alias,
    )


def _now_ms() -> int:
    return payloads.epoch_ms(datetime.now(UTC))
