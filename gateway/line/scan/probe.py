"""Probing one open line: which addresses answer, and reading what each device is.

Every address gets one small probe that all four families answer: a read of the digiLine
sensor type and sub-type (0x010A..0x010B). A digiLine answers it with data; a tecLine or
Reiss cell answers exception 02 (the address is not in its map), which still proves a
device is there. Only then (or after a broken answer, or an answer that names no
digiLine: a tecLine may answer its undocumented 0x010A with 0) does a second probe read
the tecLine/Reiss hardware and firmware versions (0x0308..0x0309). A silent address costs
one short timeout (a broken frame earns a probe one more try); everything else about a
device is read only once it has answered, with its family's processing time and one
retry: the digiLine device name (0x0000) and serial number (0x0100), the tecLine/Reiss
sensor type (0x0300), serial number (0x030C) and part number (0x0317).

I/O goes through :class:`gateway.line.boundary.Line` only; the probes use the digiLine-safe
inter-frame gap (3.5 characters, at least 2 ms) whatever is on the line.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Final

from gateway.errors import BusTimeoutError, DeviceExceptionError, FrameError
from gateway.line.boundary import RequestOptions
from gateway.line.scan.formats import probe_timeout_s
from gateway.line.scan.identify import (
    DIGILINE,
    DIGILINE_BLOCK,
    REISS,
    REISS_BLOCK,
    TECLINE,
    TECLINE_BLOCK,
    UNKNOWN,
    Families,
    decoded,
    match_identify,
    plain,
    primary_identify,
    reiss_variant,
    span,
    tecline_variant,
)
from gateway.line.scan.report import FoundDevice
from gateway.profiles import builtin_profiles
from gateway.wire import codec, frames
from gateway.wire.timing import DIGILINE_MIN_GAP_S

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Mapping

    from gateway.line.boundary import Line
    from gateway.profiles import Point, Profile

_LOGGER = logging.getLogger(__name__)

IDENTIFY_MARGIN_S: Final = 0.050  # as the bus engine's: reads of a device known to be there
IDENTIFY_ATTEMPTS: Final = 2  # a found device gets one retry per identification read

_NEITHER_FAMILY: Final = (
    "answers, but neither the digiLine sensor type (0x010A) nor the tecLine device data "
    "(0x0308) can be read"
)


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
        self._families = Families.from_profiles(
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
            note = f"answers {span(first, count)} (not in its manual) with {shown}"
            return replace(found, notes=(*found.notes, note))
        if unmatched is not None:
            why = f"the {TECLINE_BLOCK} ({span(hardware.address, tecline_count)}) cannot be read"
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
        matches, note = match_identify(self._families.digiline, codes)
        reference = matches[0] if matches else self._families.digiline[0]
        type_point = reference.point(primary_identify(reference))
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
        identified_by = f"{span(first, len(registers))} ({DIGILINE_BLOCK})"
        for name in profile.identify:
            if name != primary_identify(profile):
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
            details[point.name] = plain(
                codec.decode(point.format, registers[offset : offset + point.count])
            )
        block = firmware.last - hardware.address + 1
        identified_by = f"{span(hardware.address, block)} ({TECLINE_BLOCK})"
        reiss = self._families.reiss[0]
        type_point = reiss.point("sensor_type")
        answer = await self._identify_read(address, reiss, type_point)
        sensor_type = decoded(reiss, type_point, answer.registers)
        if isinstance(sensor_type, str) and sensor_type.strip():
            details["sensor_type"] = sensor_type
            profile, guess, notes = reiss_variant(self._families.reiss, sensor_type, address)
            family = REISS
            identified_by += f", {span(type_point.address, type_point.count)} ({REISS_BLOCK})"
        else:
            profile, guess, notes = tecline_variant(self._families.tecline, address)
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
        answer = await self._identify_read(address, profile, point)
        return decoded(profile, point, answer.registers)

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
            options = RequestOptions(timeout_s=timeout_s, gap_s=self.gap_s)
            if profile is not None:
                options.exceptions = profile.exceptions
                options.byte_count_16bit = profile.quirks.string_byte_count_16bit
            exchange = await self.line.transact(request, options)
        except DeviceExceptionError as exc:
            return _Answer(exception=exc.code)
        except BusTimeoutError:
            return _Answer()
        except FrameError as exc:
            _LOGGER.debug("address %d: broken answer: %s", address, exc)
            return _Answer(garbled=True)
        assert exchange is not None  # noqa: S101 - only broadcasts return None
        return _Answer(registers=exchange.response.registers)
