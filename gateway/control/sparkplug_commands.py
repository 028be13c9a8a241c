"""Sparkplug DCMD in: metrics written through the safe write path, the outcome reported.

A DCMD names its metrics by name or by the alias of the device's birth. The whole payload
is checked before anything is written: a payload that is not Sparkplug B protobuf, a name
or alias the device does not have, a metric that is read-only, or a value whose datatype
is not the birth's, refuses it whole: a warning names what was wrong, the refusal is
counted (``gateway_writes{kind="sparkplug", outcome="rejected"}``) and nothing reaches the
bus. Each accepted metric is then written exactly as an MQTT ``…/set`` is: resolved to a
writable point once (:meth:`SafeWriter.point`), then :meth:`SafeWriter.set` (validation,
range, flash guard, write, read-back). The outcome of each goes out as a DDATA of the value
read back and of the device's ``Write/Result`` metric (JSON: metric, status, value or
reason). Commands to one device run one after another.
"""

from __future__ import annotations

import asyncio
import logging
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Final

from gateway.errors import CommandRejectedError, GatewayError
from gateway.line.samples import json_value
from gateway.publish.sparkplug import payloads
from gateway.publish.sparkplug.session import rejected
from gateway.records.actor import Actor, Via, acting

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.control.writes import SafeWriter
    from gateway.profiles.model import Point
    from gateway.publish.sparkplug import SparkplugSink
    from gateway.publish.sparkplug.catalogue import DeviceMetrics, MetricSpec

_LOGGER = logging.getLogger(__name__)

COMMAND_TIMEOUT_S: Final = 60.0  # as MQTT set commands


class SparkplugCommands:
    """Takes a device's DCMDs, writes them through its :class:`SafeWriter`, reports."""

    def __init__(
        self,
        sink: SparkplugSink,
        writers: Mapping[str, SafeWriter],
        *,
        timeout_s: float = COMMAND_TIMEOUT_S,
        actor: Actor | None = None,
    ) -> None:
        """Write to the devices of ``writers``; report through ``sink``.

        ``actor``: who the records name for a DCMD (the session's username and client id).
        """
        self.sink = sink
        self.actor = actor or Actor(user="sparkplug", via=Via.SPARKPLUG)
        self.writers = dict(writers)
        self.timeout_s = timeout_s
        self._locks = {name: asyncio.Lock() for name in self.writers}

    async def device_command(self, device: str, payload: bytes) -> None:
        """Check the whole DCMD, then write each metric and report its outcome."""
        try:
            writes = self._accepted(device, payload)
        except CommandRejectedError as exc:
            rejected(f"DCMD to {device}", str(exc))
            self.sink.count_rejected(device)
            return
        writer = self.writers[device]
        async with self._locks[device]:
            with acting(self.actor):
                for spec, point, value in writes:
                    await self._write(writer, spec, point, value)

    def _accepted(self, device: str, payload: bytes) -> list[tuple[MetricSpec, Point, object]]:
        """Every metric of the DCMD resolved, typed and writable; else why not."""
        metrics = self.sink.catalogue.devices.get(device)
        writer = self.writers.get(device)
        if metrics is None or writer is None:
            known = ", ".join(sorted(self.writers)) or "none"
            raise CommandRejectedError(f"no device {device!r} (devices: {known})")
        writes = []
        for metric in payloads.decode_command(payload):
            spec = _resolve(metrics, metric)
            if spec.point is None or spec.label:
                hint = f" (write {spec.point.name!r} by its code)" if spec.point else ""
                raise CommandRejectedError(f"metric {spec.name!r} is read-only{hint}")
            point = writer.point(spec.point.name)  # read-only points are refused here
            value: object = payloads.command_value(metric, spec.datatype)
            if spec.bit is not None:
                value = {spec.bit: value}  # one bit of the word; the others are kept
            elif spec.datatype is payloads.SpType.DATETIME and isinstance(value, int):
                value = datetime.fromtimestamp(value / 1000, tz=UTC)
            writes.append((spec, point, value))
        return writes

    async def _write(
        self, writer: SafeWriter, spec: MetricSpec, point: Point, value: object
    ) -> None:
        device = writer.device
        result: dict[str, object] = {"metric": spec.name}
        read_back = None
        try:
            async with asyncio.timeout(self.timeout_s):
                done = await writer.set(point, value)
        except CommandRejectedError as exc:
            result |= {"status": "error", "reason": str(exc)}
            outcome = "rejected"
            rejected(f"DCMD {device}/{spec.name}", str(exc))
        except TimeoutError:
            result |= {"status": "error", "reason": f"no outcome within {self.timeout_s:g} s"}
            outcome = "failed"
            _LOGGER.warning("Sparkplug: DCMD %s/%s: %s", device, spec.name, result["reason"])
        except GatewayError as exc:
            result |= {"status": "error", "reason": str(exc)}
            outcome = "failed"
            _LOGGER.warning("Sparkplug: DCMD %s/%s failed: %s", device, spec.name, exc)
        else:
            read_back = done.value
            result |= {
                "status": "ok",
                "value": json_value(done.value),  # type: ignore[arg-type]
                "written": done.written,
            }
            if done.note:
                result["note"] = done.note
            outcome = "ok" if done.written else "unchanged"
            _LOGGER.info("Sparkplug: DCMD %s/%s = %r: %s", device, spec.name, value, outcome)
        self.sink.count_outcome(device, outcome)
        self.sink.report_write(device, spec, read_back, result)


def _resolve(metrics: DeviceMetrics, metric: payloads.CommandMetric) -> MetricSpec:
    """The device's metric a command names (by alias, else by name)."""
    if metric.alias is not None:
        spec = metrics.by_alias.get(metric.alias)
        if spec is None:
            raise CommandRejectedError(f"{metrics.device} has no metric of alias {metric.alias}")
        if metric.name is not None and metric.name != spec.name:
            raise CommandRejectedError(
                f"alias {metric.alias} is {spec.name!r}, not {metric.name!r}"
            )
        return spec
    if metric.name is None:
        raise CommandRejectedError("a metric without name or alias")
    spec = metrics.by_name.get(metric.name)
    if spec is None:
        raise CommandRejectedError(f"{metrics.device} has no metric {metric.name!r}")
    return spec
