"""What a reloaded config changes against the running one, without I/O.

A reload applies only what changed (the manual, "Reloading the config"): a bus whose settings
and devices are the same keeps its port and its schedule, a section whose settings are the
same keeps its connection. This module says which those are; the application
(:mod:`gateway.app.reload`) acts on it.

Example::

    changes = ConfigChanges.between(running, reloaded)
    changes.buses_added  # ("line3",)
    changes.sections  # frozenset({"mqtt"})
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from gateway.config.model import BusConfig, DeviceConfig, GatewayConfig

# The top-level sections besides the buses and devices, each applied on its own.
SECTIONS: Final = (
    "mqtt",
    "prometheus",
    "web",
    "logging",
    "commands",
    "feeds",
    "shared_bus",
    "sparkplug",
    "care",
)
# What a running gateway cannot change: its queue, ledger and sessions live there.
RESTART_ONLY: Final = ("state_dir",)


@dataclass(frozen=True, slots=True, kw_only=True)
class ConfigChanges:
    """Buses and devices added, removed and changed (by name), and the sections changed.

    A bus is changed when its own settings (port, line format, echo, RS485, TCP, timeouts)
    or any of its devices changed, or a device came or went; a device is changed when any
    of its settings did, its bus included.
    """

    buses_added: tuple[str, ...] = ()
    buses_removed: tuple[str, ...] = ()
    buses_changed: tuple[str, ...] = ()
    devices_added: tuple[str, ...] = ()
    devices_removed: tuple[str, ...] = ()
    devices_changed: tuple[str, ...] = ()
    sections: frozenset[str] = frozenset()
    restart_only: tuple[str, ...] = ()  # settings that take a restart; kept as they run

    @classmethod
    def between(cls, old: GatewayConfig, new: GatewayConfig) -> ConfigChanges:
        """What ``new`` changes against ``old``."""
        old_devices = {device.name: device for device in old.devices}
        new_devices = {device.name: device for device in new.devices}
        devices_changed = tuple(
            name
            for name, device in new_devices.items()
            if name in old_devices and old_devices[name] != device
        )
        old_buses = {bus.name: bus for bus in old.buses}
        new_buses = {bus.name: bus for bus in new.buses}
        buses_changed = tuple(
            name
            for name, bus in new_buses.items()
            if name in old_buses
            and _bus_differs(old_buses[name], bus, old_devices, new_devices, devices_changed)
        )
        return cls(
            buses_added=tuple(name for name in new_buses if name not in old_buses),
            buses_removed=tuple(name for name in old_buses if name not in new_buses),
            buses_changed=buses_changed,
            devices_added=tuple(name for name in new_devices if name not in old_devices),
            devices_removed=tuple(name for name in old_devices if name not in new_devices),
            devices_changed=devices_changed,
            sections=frozenset(
                section for section in SECTIONS if getattr(old, section) != getattr(new, section)
            ),
            restart_only=tuple(
                setting
                for setting in RESTART_ONLY
                if getattr(old, setting) != getattr(new, setting)
            ),
        )

    @property
    def any(self) -> bool:
        """Whether anything is to be applied."""
        return bool(self.buses_added or self.buses_removed or self.buses_changed or self.sections)

    def summary(self) -> str:
        """One line for the log: what is applied."""
        parts = [
            f"{label} {', '.join(names)}"
            for label, names in (
                ("buses added:", self.buses_added),
                ("buses removed:", self.buses_removed),
                ("buses changed:", self.buses_changed),
                ("devices added:", self.devices_added),
                ("devices removed:", self.devices_removed),
                ("devices changed:", self.devices_changed),
                ("sections changed:", tuple(sorted(self.sections))),
            )
            if names
        ]
        return "; ".join(parts) if parts else "nothing changed"


def _bus_differs(
    old: BusConfig,
    new: BusConfig,
    old_devices: dict[str, DeviceConfig],
    new_devices: dict[str, DeviceConfig],
    devices_changed: tuple[str, ...],
) -> bool:
    if old != new:
        return True
    before = {name for name, device in old_devices.items() if device.bus == old.name}
    after = {name for name, device in new_devices.items() if device.bus == new.name}
    return before != after or any(name in after for name in devices_changed)
