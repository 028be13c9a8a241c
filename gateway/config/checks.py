"""Cross-field checks: what needs the whole config, not one entry.

Bus and device names unique, buses and profiles known, one address per device on a bus,
per-point settings, flash writes and feeds that name points of the device's profile,
Sparkplug's and Prometheus' per-device groups that name configured devices, verification
rules that name a device, profile or family, a pinned
serial number the profile can read, and response timeouts that fit in the device's poll
interval.

Each check runs on every entry that can be checked, even if others are broken, and yields
``(key path, message)``; :mod:`gateway.config.loading` locates them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import (
    TYPE_CHECKING,
    Any,
    Generic,
    TypeVar,
)

from pydantic import (
    BaseModel,
    ValidationError,
)

from gateway.config.brokers import check_brokers
from gateway.config.feeds import FeedConfig, FeedSource
from gateway.config.model import BusConfig, DeviceConfig
from gateway.config.problems import close_matches
from gateway.config.serial_pin import check_serial_number
from gateway.profiles import Profile, builtin_profiles
from gateway.profiles.model import Storage
from gateway.wire.codec import NUMERIC_TYPES

if TYPE_CHECKING:
    from collections.abc import Iterator, Mapping, Sequence

    from gateway.config.problems import KeyPath


_M = TypeVar("_M", bound=BaseModel)  # a model validating one list entry


@dataclass(frozen=True, slots=True)
class _Entry(Generic[_M]):
    """One list entry: its index, its raw mapping and its model if it validates alone."""

    index: int
    raw: Mapping[str, Any]
    model: _M | None

    def text(self, key: str) -> str | None:
        value = self.raw.get(key)
        return value if isinstance(value, str) else None


def _entries(raw: object, model: type[_M]) -> list[_Entry[_M]]:
    if not isinstance(raw, list):
        return []
    entries: list[_Entry[_M]] = []
    for index, item in enumerate(raw):
        if not isinstance(item, dict):
            entries.append(_Entry(index, {}, None))
            continue
        try:
            validated: _M | None = model.model_validate(item)
        except ValidationError:
            validated = None  # its field errors are reported by the full validation
        entries.append(_Entry(index, item, validated))
    return entries


def cross_check(data: Mapping[str, Any]) -> Iterator[tuple[KeyPath, str]]:
    """Checks across entries, on every entry that can be checked even if others are broken."""
    buses = _entries(data.get("buses"), BusConfig)
    devices = _entries(data.get("devices"), DeviceConfig)
    yield from _unique_names("buses", buses)
    yield from _unique_names("devices", devices)
    bus_names = list(dict.fromkeys(n for entry in buses if (n := entry.text("name")) is not None))
    bus_models: dict[str, BusConfig] = {}
    for entry in buses:
        if entry.model is not None:
            bus_models.setdefault(entry.model.name, entry.model)
    used: dict[tuple[str, int], _Entry[DeviceConfig]] = {}
    for device in devices:
        here: KeyPath = ("devices", device.index)
        bus_name = device.text("bus")
        if bus_name is not None and bus_name not in bus_names:
            yield (*here, "bus"), _unknown_bus(bus_name, bus_names)
        profile_id = device.text("profile")
        if profile_id is not None:
            yield from _check_profile(here, profile_id, device.raw.get("points"))
            yield from _check_flash_writes(here, profile_id, device.raw.get("flash_writes"))
            yield from check_serial_number(here, _profile_or_none(profile_id), device.raw)
        model = device.model
        if model is None:
            continue
        first = used.setdefault((model.bus, model.address), device)
        if first is not device:
            yield (
                (*here, "address"),
                (
                    f"address {model.address} is already used on bus {model.bus} by "
                    f"devices[{first.index}] ({first.text('name')})"
                ),
            )
        bus = bus_models.get(model.bus)
        if bus is not None:
            yield from _check_timeout(here, model, bus)
    yield from _check_ports(buses)
    yield from _check_shared_bus(data.get("shared_bus"), devices)
    mqtt = data.get("mqtt")
    mqtt_on = not isinstance(mqtt, dict) or mqtt.get("enabled", True) is not False
    yield from _check_feeds(_entries(data.get("feeds"), FeedConfig), devices, mqtt_on=mqtt_on)
    yield from _check_sparkplug_deadbands(data.get("sparkplug"), devices)
    yield from _check_prometheus_device_groups(data.get("prometheus"), devices)
    yield from _check_care_profiles(data.get("care"))
    yield from _check_verification_rules(data.get("verification"), devices)
    yield from check_brokers(data)


def _check_prometheus_device_groups(
    prometheus: object, devices: Sequence[_Entry[DeviceConfig]]
) -> Iterator[tuple[KeyPath, str]]:
    """``prometheus.device_groups`` names configured devices."""
    if not isinstance(prometheus, dict):
        return
    groups = prometheus.get("device_groups")
    names = {n: d.text("profile") for d in devices if (n := d.text("name")) is not None}
    for device in groups if isinstance(groups, dict) else {}:
        if device not in names:
            message = f"no device {device!r}; devices: {_names(names)}"
            yield ("prometheus", "device_groups", device), message


def _check_care_profiles(care: object) -> Iterator[tuple[KeyPath, str]]:
    """``care.profiles`` names profiles or families that exist."""
    if not isinstance(care, dict) or not isinstance(profiles := care.get("profiles"), dict):
        return
    known = builtin_profiles()
    families = {profile.family for profile in known.values()}
    for name in profiles:
        if name not in known and name not in families:
            yield (
                ("care", "profiles", name),
                (
                    f"unknown profile or family {name!r}; profiles: "
                    f"{', '.join(sorted(known))}; families: {', '.join(sorted(families))}"
                ),
            )


def _check_verification_rules(
    verification: object, devices: Sequence[_Entry[DeviceConfig]]
) -> Iterator[tuple[KeyPath, str]]:
    """``verification.rules`` names configured devices, profiles or families."""
    if not isinstance(verification, dict) or not isinstance(
        rules := verification.get("rules"), dict
    ):
        return
    known = builtin_profiles()
    families = {profile.family for profile in known.values()}
    names = {n for d in devices if (n := d.text("name")) is not None}
    for name in rules:
        if name not in names and name not in known and name not in families:
            guesses = close_matches(str(name), [*names, *known, *families], 3)
            hint = f"; did you mean {', '.join(guesses)}?" if guesses else ""
            devices_said = ", ".join(sorted(names)) or "none"
            yield (
                ("verification", "rules", name),
                f"no device, profile or family {name!r}{hint} (devices: {devices_said})",
            )


def _check_ports(buses: Sequence[_Entry[BusConfig]]) -> Iterator[tuple[KeyPath, str]]:
    """One bus per port (two masters on one line collide), and RS485 mode on devices only."""
    first: dict[str, _Entry[BusConfig]] = {}
    for bus in buses:
        port = bus.text("port")
        if port is None:
            continue
        earlier = first.setdefault(port, bus)
        if earlier is not bus:
            yield (
                ("buses", bus.index, "port"),
                (
                    f"{port} is already the port of buses[{earlier.index}] "
                    f"({earlier.text('name')}): one bus per port, as it is opened exclusively"
                ),
            )
        if "://" in port and bus.raw.get("rs485") is not None:
            yield (
                ("buses", bus.index, "rs485"),
                (
                    "the kernel's RS485 mode applies to a serial device of this machine, "
                    f"not to {port}: the converter switches its own line; remove rs485"
                ),
            )


def _check_sparkplug_deadbands(
    sparkplug: object, devices: Sequence[_Entry[DeviceConfig]]
) -> Iterator[tuple[KeyPath, str]]:
    """``sparkplug.deadbands`` names configured devices and points of their profiles.

    ``sparkplug.device_groups`` names configured devices.
    """
    if not isinstance(sparkplug, dict):
        return
    profiles = {n: d.text("profile") for d in devices if (n := d.text("name")) is not None}
    groups = sparkplug.get("device_groups")
    for device in groups if isinstance(groups, dict) else {}:
        if device not in profiles:
            message = f"no device {device!r}; devices: {_names(profiles)}"
            yield ("sparkplug", "device_groups", device), message
    deadbands = sparkplug.get("deadbands")
    if not isinstance(deadbands, dict):
        return
    for device, points in deadbands.items():
        here: KeyPath = ("sparkplug", "deadbands", device)
        if device not in profiles:
            yield here, f"no device {device!r}; devices: {_names(profiles)}"
            continue
        profile = _profile_or_none(profiles[device] or "")
        if profile is None or not isinstance(points, dict):
            continue
        for point in points:
            if not profile.has_point(point):
                names = [p.name for p in profile.points]
                close = close_matches(str(point), names, n=1)
                hint = f"; did you mean {close[0]!r}?" if close else ""
                yield (*here, point), f"{profile.id} has no point {point!r}{hint}"


def _check_shared_bus(
    raw: object, devices: Sequence[_Entry[DeviceConfig]]
) -> Iterator[tuple[KeyPath, str]]:
    """Unit ids other masters can tell apart; write grants of devices that exist."""
    if not isinstance(raw, dict):
        return
    names = [n for entry in devices if (n := entry.text("name")) is not None]
    clients = raw.get("clients")
    for index, client in enumerate(clients if isinstance(clients, list) else []):
        grants = client.get("writes") if isinstance(client, dict) else None
        for number, grant in enumerate(grants if isinstance(grants, list) else []):
            device = grant.get("device") if isinstance(grant, dict) else None
            if isinstance(device, str) and device not in names:
                where: KeyPath = ("shared_bus", "clients", index, "writes", number, "device")
                yield where, f"unknown device {device!r}; devices: {', '.join(names) or 'none'}"
    if not raw.get("listen"):
        return
    units: dict[int, _Entry[DeviceConfig]] = {}
    for device in devices:
        model = device.model
        if model is None:
            continue
        unit = model.unit_id if model.unit_id is not None else model.address
        first = units.setdefault(unit, device)
        if first is not device:
            key = "unit_id" if model.unit_id is not None else "address"
            yield (
                ("devices", device.index, key),
                (
                    f"other masters reach devices[{first.index}] ({first.text('name')}) as unit "
                    f"{unit} already: give one of them a unit_id of its own for the shared bus"
                ),
            )


def _check_flash_writes(
    here: KeyPath, profile_id: str, names: object
) -> Iterator[tuple[KeyPath, str]]:
    profile = builtin_profiles().get(profile_id)
    if profile is None or not isinstance(names, list):
        return
    for index, name in enumerate(names):
        if not isinstance(name, str):
            continue
        where: KeyPath = (*here, "flash_writes", index)
        if not profile.has_point(name):
            yield where, f"profile {profile_id} has no point {name!r}"
            continue
        point = profile.point(name)
        if not point.writable:
            yield where, f"{name} is read-only; it cannot be written at all"
        elif point.storage is not Storage.FLASH:
            yield (
                where,
                f"{name} is a {point.storage} register, not flash-backed: it needs no permission",
            )


def _check_feeds(
    feeds: Sequence[_Entry[FeedConfig]], devices: Sequence[_Entry[DeviceConfig]], *, mqtt_on: bool
) -> Iterator[tuple[KeyPath, str]]:
    """A feed writes a RAM or volatile point of a known device, from a polled source."""
    by_name = {d.model.name: d.model for d in devices if d.model is not None}
    targets: dict[tuple[str, str], int] = {}
    for feed in feeds:
        model = feed.model
        if model is None:
            continue
        here: KeyPath = ("feeds", feed.index)
        device = by_name.get(model.device)
        if device is None:
            yield (*here, "device"), f"unknown device {model.device!r}; devices: {_names(by_name)}"
        else:
            yield from _check_feed_target(here, model, device)
        first = targets.setdefault((model.device, model.point), feed.index)
        if first != feed.index:
            yield (*here, "point"), f"{model.name} is already fed by feeds[{first}]"
        yield from _check_feed_source(here, model.source, by_name, mqtt_on=mqtt_on)


def _check_feed_source(
    here: KeyPath, source: FeedSource, by_name: Mapping[str, DeviceConfig], *, mqtt_on: bool
) -> Iterator[tuple[KeyPath, str]]:
    if source.topic is not None and not mqtt_on:
        yield (*here, "source", "topic"), "an MQTT source needs MQTT (mqtt.enabled is false)"
    if source.device is None or source.point is None:
        return
    origin = by_name.get(source.device)
    if origin is None:
        yield (
            (*here, "source", "device"),
            f"unknown device {source.device!r}; devices: {_names(by_name)}",
        )
        return
    profile = _profile_or_none(origin.profile)
    if profile is None:
        return
    if not profile.has_point(source.point):
        yield (
            (*here, "source", "point"),
            f"profile {origin.profile} has no point {source.point!r}",
        )
    elif not origin.interval_for(source.point).periodic:
        yield (
            (*here, "source", "point"),
            (
                f"{source.device}/{source.point} is not polled periodically, so it would "
                "never feed anything; give it an interval under the device's points"
            ),
        )


def _check_feed_target(
    here: KeyPath, feed: FeedConfig, device: DeviceConfig
) -> Iterator[tuple[KeyPath, str]]:
    profile = _profile_or_none(device.profile)
    if profile is None:
        return
    if not profile.has_point(feed.point):
        yield (*here, "point"), f"profile {device.profile} has no point {feed.point!r}"
        return
    point = profile.point(feed.point)
    if not point.writable:
        yield (*here, "point"), f"{feed.point} is read-only"
    elif point.storage is Storage.FLASH:
        free = [
            p.name
            for p in profile.points
            if p.writable and p.storage is not Storage.FLASH and p.dtype in NUMERIC_TYPES
        ]
        hint = f"; RAM or volatile points of {device.profile}: {', '.join(free)}" if free else ""
        yield (
            (*here, "point"),
            (
                f"a feed never writes to flash, and {feed.point} is flash-backed "
                f"(its cells wear out when written cyclically){hint}"
            ),
        )
    elif point.format.dtype not in NUMERIC_TYPES:
        yield (*here, "point"), f"{feed.point} is a {point.format.dtype}, not a number to feed"


def _profile_or_none(profile_id: str) -> Profile | None:
    return builtin_profiles().get(profile_id)


def _names(models: Mapping[str, object]) -> str:
    return ", ".join(models) or "none"


def _unique_names(section: str, entries: Sequence[_Entry[Any]]) -> Iterator[tuple[KeyPath, str]]:
    first: dict[str, int] = {}
    for entry in entries:
        name = entry.text("name")
        if name is None:
            continue
        if name in first:
            yield (
                (section, entry.index, "name"),
                (f"name {name} is already used by {section}[{first[name]}]"),
            )
        else:
            first[name] = entry.index


def _unknown_bus(name: str, known: Sequence[str]) -> str:
    if not known:
        return f"unknown bus {name!r}; no bus is defined under buses"
    close = close_matches(name, known, n=1)
    hint = f"did you mean {close[0]}? " if close else ""
    return f"unknown bus {name!r}; {hint}buses: {', '.join(known)}"


def _check_profile(here: KeyPath, profile_id: str, points: object) -> Iterator[tuple[KeyPath, str]]:
    profiles = builtin_profiles()
    profile = profiles.get(profile_id)
    if profile is None:
        close = close_matches(profile_id, list(profiles), n=2)
        hint = f"did you mean {' or '.join(close)}? " if close else ""
        yield (
            (*here, "profile"),
            (f"unknown profile {profile_id!r}; {hint}known: {', '.join(sorted(profiles))}"),
        )
        return
    if not isinstance(points, dict):
        return
    names = [point.name for point in profile.points]
    for name in points:
        if isinstance(name, str) and not profile.has_point(name):
            close = close_matches(name, names, n=3) or [n for n in names if name in n][:3]
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            yield (
                (*here, "points", name),
                (
                    f"profile {profile_id} has no point {name!r}{hint} "
                    f"(gateway profiles show {profile_id} lists them)"
                ),
            )


def _check_timeout(
    here: KeyPath, device: DeviceConfig, bus: BusConfig
) -> Iterator[tuple[KeyPath, str]]:
    timeout = device.response_timeout(bus)
    if timeout is None or timeout <= device.poll_interval:
        return
    if device.timeout is not None:
        key, source = "timeout", f"timeout {device.timeout:g} s"
    else:
        key, source = "poll_interval", f"bus {bus.name} timeout {bus.timeout:g} s"
    if device.min_response_time_ms:
        source += f" + min_response_time_ms {device.min_response_time_ms}"
    yield (
        (*here, key),
        (
            f"the response timeout {timeout:g} s ({source}) is longer than poll_interval "
            f"{device.poll_interval:g} s; raise poll_interval or shorten the timeout"
        ),
    )
