"""What the page shows, as JSON, read from the state without I/O.

The lines and devices with their live values, one device's register map, the bus health
figures (sensor care's documents are :mod:`~gateway.web.care`'s), and the host clock:
while it is not trusted, the page says so and offers no date-and-time point for writing
(:mod:`gateway.control.clock_trust` would refuse the write).
"""

from __future__ import annotations

import time
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Final

from gateway.control.clock_trust import time_points
from gateway.line.samples import Quality, json_value
from gateway.profiles.model import PollGroup, Storage
from gateway.publish.prometheus.health import ERROR_KINDS
from gateway.web.care import care_version
from gateway.wire.codec import BitfieldValue

if TYPE_CHECKING:
    from collections.abc import Collection, Mapping

    from gateway.line.engine.health import DeviceHealth
    from gateway.line.samples import Sample
    from gateway.line.stats import LineStats
    from gateway.profiles import Profile
    from gateway.shared.state import DeviceInfo, GatewayState

# The groups of the live table: what is measured and what the sensor says of itself.
LIVE_GROUPS: Final = frozenset({PollGroup.PROCESS.value, PollGroup.STATUS.value})


def _iso(moment: datetime | None) -> str | None:
    return moment.astimezone(UTC).isoformat(timespec="seconds") if moment else None


def sample_view(sample: Sample, *, stale: bool, now: float) -> dict[str, object]:
    """One value as the page shows it: text, unit, quality, fault, age."""
    value = sample.value
    if sample.quality is Quality.GOOD:
        text = str(json_value(value) if not isinstance(value, BitfieldValue) else value)
        if isinstance(value, float):
            text = f"{value:.6g}"
        elif value is None:
            text = "-"  # a point that holds nothing (a stamp never set)
    else:
        text = sample.fault or sample.quality.value
    view: dict[str, object] = {
        "point": sample.point,
        "text": text,
        "unit": sample.unit or "",
        "quality": "stale" if stale and sample.quality is Quality.GOOD else sample.quality.value,
        "fault": sample.fault,
        "age_s": round(max(0.0, now - sample.monotonic), 1),
        "time": _iso(sample.time),
    }
    if isinstance(value, BitfieldValue):
        view["bits"] = [{"name": name, "set": state} for name, state in value.flags]
    return view


def _errors(stats: LineStats | None, address: int | None = None) -> dict[str, int]:
    counts = dict.fromkeys(ERROR_KINDS, 0)
    if stats is None:
        return counts
    for (device, kind), count in list(stats.errors.items()):
        if address is None or device == address:
            counts[str(kind)] = counts.get(str(kind), 0) + count
    return counts


def _newest_good(state: GatewayState) -> dict[tuple[str, str], Sample]:
    """Each device's newest good sample: its last good response (one pass over them all)."""
    newest: dict[tuple[str, str], Sample] = {}
    for (bus, device, _), sample in list(state.last_good.items()):
        held = newest.get((bus, device))
        if held is None or sample.monotonic > held.monotonic:
            newest[bus, device] = sample
    return newest


def _device_heading(info: DeviceInfo) -> dict[str, object]:
    """What both views of a device start with: where it is, what it is, whether it answers."""
    return {
        "bus": info.bus,
        "name": info.name,
        "profile": info.profile,
        "address": info.address,
        "online": info.online,
        "reason": info.reason,
    }


def _device_view(
    info: DeviceInfo,
    state: GatewayState,
    health: DeviceHealth | None,
    last_good: Sample | None,
    now: float,
) -> dict[str, object]:
    samples = state.device_samples(info.bus, info.name)
    values = [
        sample_view(s, stale=state.is_stale(s, now), now=now)
        for s in samples.values()
        if s.group in LIVE_GROUPS
    ]
    stats = state.lines.get(info.bus)
    return {
        **_device_heading(info),
        "values": values,
        "last_good": _iso(last_good.time) if last_good else None,
        "last_good_age_s": round(now - last_good.monotonic, 1) if last_good else None,
        "errors": _errors(stats, info.address),
        "requests": stats.requests[info.address] if stats else 0,
        "retries": stats.retries[info.address] if stats else 0,
        "lag_s": round(health.lag_s, 3) if health else None,
        "missed_deadlines": health.missed_deadlines if health else 0,
        "failures_in_a_row": health.failures_in_a_row if health else 0,
    }


def _line_view(name: str, stats: LineStats, paused: str | None, now: float) -> dict[str, object]:
    requests = sum(stats.requests.values())
    latency = sum(stats.latency_sum_s.values())
    responses = sum(stats.responses.values())
    return {
        "name": name,
        "port_open": stats.port_open,
        "port_failures": stats.port_failures,
        "requests": requests,
        "responses": responses,
        "retries": sum(stats.retries.values()),
        "errors": _errors(stats),
        "utilisation": round(stats.utilisation(now), 4),
        "mean_latency_ms": round(1000 * latency / responses, 1) if responses else None,
        "paused": paused,
    }


def overview(state: GatewayState, paused: Mapping[str, str] | None = None) -> dict[str, object]:
    """Every line and device, with the live values: what ``/api/state`` and the events send.

    ``paused`` names the lines whose polling is stopped now, and why (a scan).
    """
    now = time.monotonic()
    paused = paused or {}
    health = {(h.bus, h.device): h for h in state.health()}
    lines = [_line_view(name, stats, paused.get(name), now) for name, stats in state.lines.items()]
    newest = _newest_good(state)
    devices = [
        _device_view(info, state, health.get(key), newest.get(key), now)
        for key, info in list(state.devices.items())
    ]
    return {
        "time": _iso(datetime.now(tz=UTC)),
        "uptime_s": round(now - state.started, 1),
        "mqtt": _broker_view(state),
        "lines": lines,
        "devices": devices,
        "clock": state.clock.status().as_dict(),
        "care_version": care_version(state),  # the page asks /api/care again when it changes
    }


def _broker_view(state: GatewayState) -> dict[str, object]:
    """The MQTT connection: which server of the list, how often it moved, a stand-down.

    With one server the page says only connected or not; with a list it names the server
    in use and its place, as ``/healthz`` and ``gateway_mqtt_server`` do.
    """
    mqtt = state.mqtt
    view: dict[str, object] = {
        "enabled": mqtt.enabled,
        "connected": mqtt.connected,
        "queue_depth": mqtt.queue_depth,
        "server": mqtt.server,
        "servers": len(mqtt.servers),
        "position": mqtt.servers.index(mqtt.server) + 1 if mqtt.server in mqtt.servers else 0,
        "switches": mqtt.switches,
        "identity_conflict": mqtt.identity_conflict,
    }
    sparkplug = state.sparkplug
    if sparkplug.enabled:
        view["sparkplug"] = {
            "connected": sparkplug.connected,
            "host_online": sparkplug.host_online,
            "server": sparkplug.server,
            "switches": sparkplug.switches,
        }
    return view


def register_map(
    info: DeviceInfo,
    profile: Profile,
    state: GatewayState,
    *,
    writable_by_page: bool,
    flash_allowed: Collection[str] = (),
) -> dict[str, object]:
    """One device: identity and every point of its register map with its latest value.

    A flash-backed point not in ``flash_allowed`` (the device's ``flash_writes``) is not
    offered for writing: the write path would refuse it, so the page says why instead.
    """
    now = time.monotonic()
    samples = state.device_samples(info.bus, info.name)
    points = []
    identity = {}
    dated = {p.name for p in time_points(profile)}
    clock_trusted = not dated or state.clock.status().trusted
    for point in profile.points:
        sample = samples.get(point.name)
        view = sample_view(sample, stale=state.is_stale(sample, now), now=now) if sample else None
        writable = point.writable and not point.view
        refused = (
            "flash, not in flash_writes"
            if point.storage is Storage.FLASH and point.name not in flash_allowed
            else None
        )
        if point.name in dated and not clock_trusted:
            refused = "a date, and the host clock is not synchronised"
        if point.group is PollGroup.IDENTITY and view is not None:
            identity[point.name] = view["text"]
        points.append(
            {
                "name": point.name,
                "address": f"0x{point.address:04X}",
                "type": point.dtype.value,
                "count": point.count,
                "access": point.access.value,
                "unit": point.unit or (view["unit"] if view else "") or "",
                "storage": point.storage.value if point.storage else "",
                "group": point.group.value,
                "description": point.description,
                "writable": writable and writable_by_page and not refused,
                "refused": refused if writable else None,
                "value": view,
            }
        )
    return {
        **_device_heading(info),
        "identity": identity,
        "points": points,
    }
