"""What a scan found: each device with what identified it, the report, the config snippet."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import yaml

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.wire.timing import LineFormat


@dataclass(frozen=True, slots=True, kw_only=True)
class FoundDevice:
    """A device that answered, and what it was identified as.

    ``profile`` is ``None`` for a device no profile fits (a digiLine pH sensor, a device of
    another make); ``guess`` says the profile could not be read from the device itself.
    ``identified_by`` names the registers the family and profile were read from, e.g.
    ``0x0308..0x0309 (tecLine device data)``; empty when none identified it.
    """

    address: int
    line: LineFormat
    family: str  # digiline, tecline, reiss or unknown: the stem of the generated name
    profile: str | None
    guess: bool = False
    identified_by: str = ""
    details: Mapping[str, object] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        """The device name the config snippet gives it: ``<family>_<address>``."""
        return f"{self.family}_{self.address}"

    def details_text(self, sep: str = ", ") -> str:
        """What identified the device and ``key=value`` pairs of what it told about itself.

        The identification column of the scan table, and logs.
        """
        told = [f"{k}={v}" for k, v in self.details.items() if v is not None]
        by = [f"identified by {self.identified_by}"] if self.identified_by else []
        return sep.join([*by, *told])

    def as_dict(self) -> dict[str, Any]:
        """The device as JSON-ready data."""
        return {
            "address": self.address,
            "format": str(self.line),
            "baudrate": self.line.baudrate,
            "parity": self.line.parity,
            "stopbits": self.line.stopbits,
            "family": self.family,
            "profile": self.profile,
            "guess": self.guess,
            "identified_by": self.identified_by,
            "name": self.name,
            "details": dict(self.details),
            "notes": list(self.notes),
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class ScanReport:
    """Everything a scan found on one port, and what it cost."""

    port: str
    formats: tuple[LineFormat, ...]
    addresses: tuple[int, ...]
    devices: tuple[FoundDevice, ...]
    garbled: tuple[tuple[LineFormat, int], ...] = ()  # answers that were not valid frames
    requests: int = 0
    elapsed_s: float = 0.0

    @property
    def config_format(self) -> LineFormat | None:
        """The format the config snippet uses: the one most configurable devices answered in."""
        counts: dict[LineFormat, int] = {}
        for device in self.devices:
            if device.profile is not None:
                counts[device.line] = counts.get(device.line, 0) + 1
        if not counts:
            return None
        return max(counts, key=lambda fmt: (counts[fmt], -self.formats.index(fmt)))

    def config_yaml(self, *, bus_name: str = "line1") -> str:
        """A config snippet to paste: one bus in the chosen format, its devices.

        Devices without a profile, or found only in another format, are listed as comments:
        one line carries one format. Each device's serial number, where it was read, is
        pinned (``serial_number:``), so a swapped adapter cannot pass one line's sensors off
        as the other's.
        """
        chosen = self.config_format
        if chosen is None:
            return ""
        on_bus = [d for d in self.devices if d.line == chosen and d.profile is not None]
        lines = [
            f"# gateway scan of {self.port}: {len(on_bus)} device(s) at {chosen}",
            "buses:",
            *_yaml_item(
                {
                    "name": bus_name,
                    "port": self.port,
                    "baudrate": chosen.baudrate,
                    "parity": chosen.parity,
                    "stopbits": chosen.stopbits,
                }
            ),
            "devices:",
        ]
        for device in on_bus:
            if device.identified_by:
                lines.append(f"  # identified by {device.identified_by}")  # the item below
            item = _yaml_item(
                {
                    "name": device.name,
                    "bus": bus_name,
                    "address": device.address,
                    "profile": device.profile,
                }
            )
            if device.guess:
                item[-1] += "  # guess: check the nameplate"
            lines.extend(item)
            lines.extend(_serial_line(device))
        taken = {device.address for device in on_bus}
        for device in self.devices:
            if device in on_bus or device.address in taken:
                continue  # the same device seen again in a similar format (8N1 and 8N2)
            if device.profile is None:
                why = "no profile fits: " + "; ".join(device.notes)
            else:
                why = f"{device.profile} answers at {device.line}, not {chosen}"
            lines.append(f"  # address {device.address}: {why}")
        return "\n".join(lines) + "\n"

    def as_dict(self) -> dict[str, Any]:
        """The report as JSON-ready data: devices and the config snippet first."""
        return {
            "devices": [device.as_dict() for device in self.devices],
            "config": self.config_yaml(),
            "port": self.port,
            "formats": [str(fmt) for fmt in self.formats],
            "addresses": len(self.addresses),
            "garbled": [{"format": str(fmt), "address": a} for fmt, a in self.garbled],
            "requests": self.requests,
            "elapsed_s": round(self.elapsed_s, 3),
        }


def _serial_line(device: FoundDevice) -> list[str]:
    """``serial_number:`` as read, quoted if text (digits unquoted would be a number to YAML)."""
    serial = device.details.get("serial_number")
    if isinstance(serial, str) and serial.strip():
        # JSON's double-quoted string is YAML's: "0104714601000000201" stays text.
        return [f"    serial_number: {json.dumps(serial.strip())}"]
    if isinstance(serial, int) and not isinstance(serial, bool):
        return [f"    serial_number: {serial}"]
    return []


def _yaml_item(mapping: Mapping[str, object]) -> list[str]:
    """One sequence item in block style, each value quoted by the YAML emitter as needed."""
    lines = []
    for index, (key, value) in enumerate(mapping.items()):
        text = yaml.safe_dump({key: value}, default_flow_style=False, allow_unicode=True)
        lines.append(("  - " if index == 0 else "    ") + text.strip())
    return lines
