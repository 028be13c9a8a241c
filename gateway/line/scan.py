"""Bus scan: which addresses answer on a line, in which format, and what each sensor is.

Every address of the range gets one small probe that all four families answer: a read of
the digiLine sensor type and sub-type (0x010A..0x010B). A digiLine answers it with data; a
tecLine or Reiss cell answers exception 02 (the address is not in its map), which still
proves a device is there. Only then (or after a broken answer, or an answer that names no
digiLine: a tecLine may answer its undocumented 0x010A with 0) does a second probe read
the tecLine/Reiss hardware and firmware versions (0x0308..0x0309): every manual says an
unmapped address is answered with exception 02, so a silent address costs one short
timeout (a broken frame earns a probe one more try); everything else about a device is
read only once it has answered, with its family's processing time and one retry. Each
device found says which registers identified it (``identified_by``).

Identification, from the registers the manuals name for it (specs/README.md):

- digiLine: the sensor type and sub-type codes select the profile whose ``identify``
  matches (S10, H10, H20); the device name (0x0000) and serial number (0x0100) are read.
- tecLine / Reiss: a Reiss cell has a sensor type string at 0x0300 (``CP4.0N-M0``, the
  suffix tells M0c from M3c), which a tecLine does not have. The tecLine variants share one
  register map and no register tells them apart: the variant whose factory address equals
  the found address is reported, or Cl2, and either way marked as a guess. Serial number
  (0x030C), firmware (0x0309) and part number (0x0317) are read.

I/O goes through :class:`gateway.line.port.Line` only; the probes use the digiLine-safe
inter-frame gap (3.5 characters, at least 2 ms) whatever is on the line.

Example::

    report = await scan(
        "/dev/ttyUSB0",
        formats=[LineFormat(baudrate=9600)],
        addresses=parse_addresses("1-247"),
    )
    print(report.config_yaml())
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Final

import yaml

from gateway.config import BAUDRATES, MAX_RESPONSE_TIMEOUT_S
from gateway.errors import (
    BusTimeoutError,
    ConfigError,
    DecodeError,
    DeviceExceptionError,
    FrameError,
)
from gateway.line.port import Line
from gateway.profiles import builtin_profiles
from gateway.wire import codec, frames
from gateway.wire.timing import DIGILINE_MIN_GAP_S, LineFormat

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Mapping, Sequence

    from gateway.profiles import Point, Profile

_LOGGER = logging.getLogger(__name__)

FIRST_ADDRESS: Final = 1
LAST_ADDRESS: Final = 247  # Modbus over serial line 2.2: unicast addresses 1..247
# A probe's answer must start within the digiLine t1 (max. 25 ms, S10 and H10/H20 manuals
# 5.1) with 5 ms to spare; the tecLine manual gives no figure. A sensor with a digiLine
# minimum response time (0x0305) set needs --timeout.
PROBE_RESPONSE_S: Final = 0.030
PROBE_MARGIN_S: Final = 0.010  # event-loop timers and USB adapters add a few ms
IDENTIFY_MARGIN_S: Final = 0.050  # as the bus engine's: reads of a device known to be there
IDENTIFY_ATTEMPTS: Final = 2  # a found device gets one retry per identification read
PROBE_REGISTERS: Final = 2

DIGILINE: Final = "digiline"
TECLINE: Final = "tecline"
REISS: Final = "reiss"
UNKNOWN: Final = "unknown"
TECLINE_FAMILY: Final = "jumo-tecline"
REISS_FAMILY: Final = "reiss-m0c-m3c"
# Reiss manual 4 "Gerätedaten", 0x0300 Sensortyp, example "CP4.0N-M0": the suffix names the
# variant (M0 = M0c, M3 = M3c).
_REISS_SUFFIX = re.compile(r"-M([03])\b")
_REISS_VARIANTS: Final = {"0": "reiss-m0c", "3": "reiss-m3c"}

_NEITHER_FAMILY: Final = (
    "answers, but neither the digiLine sensor type (0x010A) nor the tecLine device data "
    "(0x0308) can be read"
)
# The identity blocks, as ``identified_by`` names them (specs/README.md, "Identification").
DIGILINE_BLOCK: Final = "digiLine sensor type"
TECLINE_BLOCK: Final = "tecLine device data"
REISS_BLOCK: Final = "Reiss sensor type"

_RANGE = re.compile(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?")
_FORMAT_LABEL = re.compile(r"8([neo])([12])")
_BAUD_LABEL = re.compile(r"baud_(\d+)")

# --- input ------------------------------------------------------------------------------


def parse_addresses(text: str) -> tuple[int, ...]:
    """Addresses from ``1-247``, ``7`` or ``1-10,20,30-40``: sorted, each once.

    Raises :class:`ConfigError` naming the option for anything else.
    """
    addresses: set[int] = set()
    for part in text.split(","):
        match = _RANGE.fullmatch(part)
        if match is None:
            raise ConfigError(
                f"--addresses {text!r}: expected N, N-M or a comma-separated list of them, "
                "e.g. 1-247 or 1-10,20"
            )
        first = int(match[1])
        last = int(match[2]) if match[2] is not None else first
        if not FIRST_ADDRESS <= first <= last <= LAST_ADDRESS:
            raise ConfigError(
                f"--addresses {text!r}: {part.strip()} is not a range within "
                f"{FIRST_ADDRESS}..{LAST_ADDRESS} (first <= last)"
            )
        addresses.update(range(first, last + 1))
    return tuple(sorted(addresses))


def supported_formats(profiles: Mapping[str, Profile] | None = None) -> tuple[LineFormat, ...]:
    """Every line format some family can be set to, from the profiles' interface registers.

    The baud rate enums (digiLine 0x0301, tecLine/Reiss 0x0401) and the data format enums
    (digiLine 0x0302, tecLine/Reiss 0x0402, labels such as ``8e1``) are the source, so a
    profile that adds a rate (Reiss 115200) adds it here. Ordered by baud rate, then
    8N1, 8E1, 8O1, 8N2.
    """
    profiles = builtin_profiles() if profiles is None else profiles
    rates: set[int] = set()
    characters: set[tuple[str, int]] = set()
    for profile in profiles.values():
        for point in profile.points:
            labels = point.format.enum.values()
            for label in labels:
                if (baud := _BAUD_LABEL.fullmatch(label)) is not None:
                    rates.add(int(baud[1]))
                elif (character := _FORMAT_LABEL.fullmatch(label)) is not None:
                    characters.add((character[1].upper(), int(character[2])))
    order = {("N", 1): 0, ("E", 1): 1, ("O", 1): 2, ("N", 2): 3}
    return tuple(
        LineFormat(baudrate=rate, parity=parity, stopbits=stopbits)  # type: ignore[arg-type]
        for rate in sorted(rates)
        for parity, stopbits in sorted(characters, key=lambda c: order.get(c, len(order)))
    )


def scan_formats(
    *, baudrate: int, parity: str, stopbits: int, every: bool = False
) -> tuple[LineFormat, ...]:
    """The given format, checked, and with ``every`` all :func:`supported_formats` after it.

    Raises :class:`ConfigError` naming the option for a format the config would refuse.
    """
    if parity not in {"N", "E", "O"} or stopbits not in {1, 2}:
        raise ConfigError("--parity must be N, E or O and --stopbits 1 or 2")
    if baudrate not in BAUDRATES:
        raise ConfigError(f"--baudrate {baudrate}: use one of {', '.join(map(str, BAUDRATES))}")
    given = LineFormat(baudrate=baudrate, parity=parity, stopbits=stopbits)  # type: ignore[arg-type]
    if not every:
        return (given,)
    return (given, *(fmt for fmt in supported_formats() if fmt != given))


def probe_timeout_s(line: LineFormat) -> float:
    """A probe's response timeout: its answer's wire time + 30 ms + a margin."""
    answer_bytes = 5 + 2 * PROBE_REGISTERS  # address, function, count, data, CRC
    return line.wire_s(answer_bytes) + PROBE_RESPONSE_S + PROBE_MARGIN_S


# --- results ----------------------------------------------------------------------------


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
        one line carries one format.
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


def _yaml_item(mapping: Mapping[str, object]) -> list[str]:
    """One sequence item in block style, each value quoted by the YAML emitter as needed."""
    lines = []
    for index, (key, value) in enumerate(mapping.items()):
        text = yaml.safe_dump({key: value}, default_flow_style=False, allow_unicode=True)
        lines.append(("  - " if index == 0 else "    ") + text.strip())
    return lines


# --- probing one line -------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Answer:
    """What one read got: registers, an exception code, a broken frame, or nothing."""

    registers: tuple[int, ...] | None = None
    exception: int | None = None
    garbled: bool = False

    @property
    def present(self) -> bool:
        """Whether a device certainly answered (with data or an exception)."""
        return self.registers is not None or self.exception is not None


@dataclass(frozen=True, slots=True)
class _Families:
    """The profiles a scan identifies with, and the points it reads, resolved once."""

    digiline: tuple[Profile, ...]  # profiles with ``identify`` codes
    tecline: tuple[Profile, ...]
    reiss: tuple[Profile, ...]

    @classmethod
    def from_profiles(cls, profiles: Mapping[str, Profile]) -> _Families:
        ordered = sorted(profiles.values(), key=lambda p: p.id)
        return cls(
            digiline=tuple(p for p in ordered if p.identify),
            tecline=tuple(p for p in ordered if p.family == TECLINE_FAMILY),
            reiss=tuple(p for p in ordered if p.family == REISS_FAMILY),
        )

    def digiline_probe(self) -> tuple[int, int]:
        """First address and count covering every identify point (0x010A..0x010B)."""
        reference = self.digiline[0]
        addresses = sorted(reference.point(name).address for name in reference.identify)
        return addresses[0], addresses[-1] - addresses[0] + 1

    def tecline_probe(self) -> tuple[Point, Point]:
        """Hardware and firmware version (0x0308, 0x0309)."""
        reference = self.tecline[0]
        return reference.point("hardware_version"), reference.point("firmware_version")


class Scanner:
    """Probes the addresses of one open :class:`Line`, in the line's format."""

    def __init__(
        self,
        line: Line,
        *,
        timeout_s: float | None = None,
        profiles: Mapping[str, Profile] | None = None,
    ) -> None:
        """Probe with ``timeout_s`` (default :func:`probe_timeout_s` of the line's format)."""
        self.line = line
        self.timeout_s = timeout_s if timeout_s is not None else probe_timeout_s(line.format)
        self.gap_s = line.format.frame_gap_s(DIGILINE_MIN_GAP_S)
        self.garbled: list[int] = []
        self._families = _Families.from_profiles(
            builtin_profiles() if profiles is None else profiles
        )

    async def sweep(
        self, addresses: Iterable[int], *, progress: Callable[[int, int], None] | None = None
    ) -> list[FoundDevice]:
        """Probe each address in turn; ``progress(address, found_so_far)`` after each."""
        found: list[FoundDevice] = []
        for address in addresses:
            device = await self.probe(address)
            if device is not None:
                found.append(device)
            if progress is not None:
                progress(address, len(found))
        return found

    async def probe(self, address: int) -> FoundDevice | None:
        """Find out whether ``address`` answers and what it is; ``None`` when silent.

        Every family's identity block is tried before a device is given up as unknown.
        """
        first, count = self._families.digiline_probe()
        digiline = await self._probe_read(address, first, count)
        if digiline.registers is not None:
            found = await self._digiline(address, first, digiline.registers)
            if found.profile is not None:
                return found
            # Not necessarily a digiLine: the tecLine and Reiss manuals do not document
            # 0x010A, and a real cell may answer it with 0 instead of exception 02.
            return await self._not_digiline(address, digiline, unmatched=found)
        if not digiline.present and not digiline.garbled:
            return None  # silent: nothing is there
        return await self._not_digiline(address, digiline)

    async def _not_digiline(
        self, address: int, digiline: _Answer, *, unmatched: FoundDevice | None = None
    ) -> FoundDevice | None:
        """Identify a device the digiLine probe did not: by the tecLine device data.

        ``unmatched`` is what the digiLine codes it answered said (no profile has them).
        """
        first, count = self._families.digiline_probe()
        if digiline.exception not in {None, frames.ILLEGAL_ADDRESS}:
            _LOGGER.debug(
                "address %d: exception %s to the digiLine probe", address, digiline.exception
            )
        hardware, firmware = self._families.tecline_probe()
        tecline_count = firmware.last - hardware.address + 1
        tecline = await self._probe_read(address, hardware.address, tecline_count)
        if tecline.registers is not None:
            found = await self._tecline(address, tecline.registers)
            if unmatched is None:
                return found
            shown = ", ".join(str(word) for word in digiline.registers or ())
            note = f"answers {_span(first, count)} (not in its manual) with {shown}"
            return replace(found, notes=(*found.notes, note))
        if unmatched is not None:
            why = f"the {TECLINE_BLOCK} ({_span(hardware.address, tecline_count)}) cannot be read"
            return replace(unmatched, notes=(*unmatched.notes, why))
        if digiline.present or tecline.present:
            codes = sorted({a.exception for a in (digiline, tecline) if a.exception is not None})
            return FoundDevice(
                address=address,
                line=self.line.format,
                family=UNKNOWN,
                profile=None,
                details={"exceptions": codes},
                notes=(_NEITHER_FAMILY,),
            )
        if digiline.garbled or tecline.garbled:
            self.garbled.append(address)
        return None

    # --- families ------------------------------------------------------------------------

    async def _digiline(self, address: int, first: int, registers: tuple[int, ...]) -> FoundDevice:
        codes = dict(enumerate(registers, start=first))
        matches, note = _match_identify(self._families.digiline, codes)
        reference = matches[0] if matches else self._families.digiline[0]
        type_point = reference.point(_primary_identify(reference))
        type_code = codes[type_point.address]
        label = str(codec.decode(type_point.format, (type_code,)))
        details: dict[str, object] = {"sensor_type": label}
        if not matches:
            known = type_code in type_point.format.enum
            return FoundDevice(
                address=address,
                line=self.line.format,
                family=DIGILINE if known else UNKNOWN,
                profile=None,
                details=details,
                notes=(f"sensor type {label} (code {type_code} at 0x{first:04X}): no profile",),
            )
        profile = matches[0]
        identified_by = f"{_span(first, len(registers))} ({DIGILINE_BLOCK})"
        for name in profile.identify:
            if name != _primary_identify(profile):
                point = profile.point(name)
                details[name] = str(codec.decode(point.format, (codes[point.address],)))
        for name in ("device_name", "serial_number"):
            details[name] = await self._point(address, profile, name)
        return FoundDevice(
            address=address,
            line=self.line.format,
            family=DIGILINE,
            profile=profile.id,
            guess=len(matches) > 1,
            identified_by=identified_by,
            details=details,
            notes=(note,) if note else (),
        )

    async def _tecline(self, address: int, registers: tuple[int, ...]) -> FoundDevice:
        hardware, firmware = self._families.tecline_probe()
        details: dict[str, object] = {}
        for point in (hardware, firmware):
            offset = point.address - hardware.address
            details[point.name] = _plain(
                codec.decode(point.format, registers[offset : offset + point.count])
            )
        block = firmware.last - hardware.address + 1
        identified_by = f"{_span(hardware.address, block)} ({TECLINE_BLOCK})"
        reiss = self._families.reiss[0]
        type_point = reiss.point("sensor_type")
        answer = await self._identify_read(address, reiss, type_point)
        sensor_type = _decoded(reiss, type_point, answer)
        if isinstance(sensor_type, str) and sensor_type.strip():
            details["sensor_type"] = sensor_type
            profile, guess, notes = _reiss_variant(self._families.reiss, sensor_type, address)
            family = REISS
            identified_by += f", {_span(type_point.address, type_point.count)} ({REISS_BLOCK})"
        else:
            profile, guess, notes = _tecline_variant(self._families.tecline, address)
            family = TECLINE
            if answer.exception is None:  # no answer at all: it may still be a Reiss
                notes = (*notes, "the Reiss sensor type (0x0300) could not be read")
        for name in ("serial_number", "part_number"):
            details[name] = await self._point(address, profile, name)
        return FoundDevice(
            address=address,
            line=self.line.format,
            family=family,
            profile=profile.id,
            guess=guess,
            identified_by=identified_by,
            details=details,
            notes=notes,
        )

    # --- reads ---------------------------------------------------------------------------

    async def _point(self, address: int, profile: Profile, name: str) -> object:
        """A point of a found device, decoded; ``None`` when it cannot be read."""
        point = profile.point(name)
        return _decoded(profile, point, await self._identify_read(address, profile, point))

    async def _identify_read(self, address: int, profile: Profile, point: Point) -> _Answer:
        """Read a point of a device known to be there: the profile's timing, one retry."""
        answer_bytes = 6 + 2 * point.count  # with room for the digiLine two-byte count
        timeout_s = max(
            self.timeout_s,
            self.line.format.wire_s(answer_bytes)
            + profile.timing.processing_time_s
            + IDENTIFY_MARGIN_S,
        )
        answer = _Answer()
        for _attempt in range(IDENTIFY_ATTEMPTS):
            answer = await self._read(
                address, point.address, point.count, timeout_s=timeout_s, profile=profile
            )
            if answer.present:
                break
        return answer

    async def _probe_read(self, address: int, first: int, count: int) -> _Answer:
        """A probe: silence is final, a broken frame gets one more try (a noisy line)."""
        answer = await self._read(address, first, count, timeout_s=self.timeout_s)
        if answer.garbled:
            retry = await self._read(address, first, count, timeout_s=self.timeout_s)
            if retry.present:
                return retry
        return answer

    async def _read(
        self,
        address: int,
        first: int,
        count: int,
        *,
        timeout_s: float,
        profile: Profile | None = None,
    ) -> _Answer:
        request = frames.read_request(address, first, count)
        try:
            exchange = await self.line.transact(
                request,
                timeout_s=timeout_s,
                gap_s=self.gap_s,
                exceptions=profile.exceptions if profile else frames.STANDARD_EXCEPTIONS,
                byte_count_16bit=profile.quirks.string_byte_count_16bit if profile else False,
            )
        except DeviceExceptionError as exc:
            return _Answer(exception=exc.code)
        except BusTimeoutError:
            return _Answer()
        except FrameError as exc:
            _LOGGER.debug("address %d: broken answer: %s", address, exc)
            return _Answer(garbled=True)
        assert exchange is not None  # noqa: S101 - only broadcasts return None
        return _Answer(registers=exchange.response.registers)


def _span(first: int, count: int) -> str:
    """Registers as ``0x0308..0x0309`` (one: ``0x0300``), as the manuals print them."""
    last = first + count - 1
    return f"0x{first:04X}" if count == 1 else f"0x{first:04X}..0x{last:04X}"


def _plain(value: codec.Decoded) -> object:
    """A decoded value as JSON-ready data: numbers and text as they are, the rest as text."""
    return value if value is None or isinstance(value, (str, int, float)) else str(value)


def _decoded(profile: Profile, point: Point, answer: _Answer) -> object:
    """The point's value from an answer; ``None`` without registers or when undecodable."""
    if answer.registers is None:
        return None
    try:
        value = codec.decode(point.format, answer.registers, float_order=profile.float_order)
    except DecodeError as exc:
        _LOGGER.debug("%s: %s", point.name, exc)
        return None
    return _plain(value)


def _primary_identify(profile: Profile) -> str:
    """The identify point with the lowest address: the family's sensor type."""
    return min(profile.identify, key=lambda name: profile.point(name).address)


def _match_identify(
    candidates: Sequence[Profile], codes: Mapping[int, int]
) -> tuple[list[Profile], str]:
    """Profiles whose identify codes all match; else those whose sensor type matches."""

    def matches(profile: Profile, names: Iterable[str]) -> bool:
        return all(
            codes.get(profile.point(name).address) == profile.identify[name] for name in names
        )

    exact = [p for p in candidates if matches(p, p.identify)]
    if exact:
        return exact, ""
    partial = [p for p in candidates if matches(p, [_primary_identify(p)])]
    if not partial:
        return [], ""
    shown = ", ".join(f"0x{a:04X}={code}" for a, code in sorted(codes.items()))
    return partial, f"sensor type known but sub-type unexpected ({shown})"


def _by_factory_address(profiles: Sequence[Profile], address: int) -> Profile | None:
    for profile in profiles:
        if profile.serial is not None and profile.serial.address == address:
            return profile
    return None


def _tecline_variant(
    profiles: Sequence[Profile], address: int
) -> tuple[Profile, bool, tuple[str, ...]]:
    """The tecLine registers do not name the variant: go by the factory address, else Cl2."""
    by_address = _by_factory_address(profiles, address)
    if by_address is not None:
        note = (
            f"tecLine variant guessed from the factory default address {address} "
            f"({by_address.id}); no register tells the variants apart"
        )
        return by_address, True, (note,)
    default = next(p for p in profiles if p.id == "jumo-tecline-cl2")
    note = (
        "tecLine variant cannot be read from the registers: jumo-tecline-cl2 is a guess; "
        "check the nameplate (Cl2, TC, ClO2, O3, H2O2, PAA, Br, Cl2 OM)"
    )
    return default, True, (note,)


def _reiss_variant(
    profiles: Sequence[Profile], sensor_type: str, address: int
) -> tuple[Profile, bool, tuple[str, ...]]:
    """M0c or M3c from the sensor type string's suffix; else by factory address, a guess."""
    by_id = {p.id: p for p in profiles}
    suffix = _REISS_SUFFIX.search(sensor_type)
    if suffix is not None and _REISS_VARIANTS[suffix[1]] in by_id:
        return by_id[_REISS_VARIANTS[suffix[1]]], False, ()
    guess = _by_factory_address(profiles, address) or profiles[0]
    note = f"Reiss sensor type {sensor_type!r} names no variant: {guess.id} is a guess"
    return guess, True, (note,)


# --- the whole scan ---------------------------------------------------------------------


async def scan(
    port: str,
    *,
    formats: Sequence[LineFormat],
    addresses: Sequence[int],
    timeout_s: float | None = None,
    progress: Callable[[LineFormat, int, int], None] | None = None,
    line_factory: Callable[..., Line] = Line,
) -> ScanReport:
    """Open ``port`` in each format in turn and probe every address.

    ``progress(format, address, found_so_far)`` is called after each address, with the
    devices found in all formats so far. A port that
    cannot be opened raises :class:`gateway.errors.BusClosedError` before anything is sent.
    ``line_factory(port=..., line=...)`` builds each :class:`Line` (a seam for tests).
    """
    if timeout_s is not None and not 0 < timeout_s <= MAX_RESPONSE_TIMEOUT_S:
        raise ConfigError(
            f"--timeout {timeout_s:g}: expected more than 0 and at most "
            f"{MAX_RESPONSE_TIMEOUT_S:g} s"
        )
    started = time.monotonic()
    devices: list[FoundDevice] = []
    garbled: list[tuple[LineFormat, int]] = []
    requests = 0
    for fmt in formats:
        line = line_factory(port=port, line=fmt)
        await line.open()
        try:
            scanner = Scanner(line, timeout_s=timeout_s)

            def report(
                address: int, found: int, fmt: LineFormat = fmt, before: int = len(devices)
            ) -> None:
                if progress is not None:
                    progress(fmt, address, before + found)

            devices.extend(await scanner.sweep(addresses, progress=report))
            garbled.extend((fmt, address) for address in scanner.garbled)
        finally:
            requests += sum(line.stats.requests.values())
            await line.close()
    return ScanReport(
        port=port,
        formats=tuple(formats),
        addresses=tuple(addresses),
        devices=tuple(devices),
        garbled=tuple(garbled),
        requests=requests,
        elapsed_s=time.monotonic() - started,
    )
