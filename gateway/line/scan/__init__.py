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

I/O goes through :class:`gateway.line.boundary.Line` only; the probes use the digiLine-safe
inter-frame gap (3.5 characters, at least 2 ms) whatever is on the line.

The pieces: the addresses and line formats to try in :mod:`~gateway.line.scan.formats`,
identification without I/O in :mod:`~gateway.line.scan.identify`, probing one open line
in :mod:`~gateway.line.scan.probe`, what was found and the config snippet in
:mod:`~gateway.line.scan.report`, the whole scan over every format in
:mod:`~gateway.line.scan.sweep`. Import from here.

Example::

    report = await scan(
        "/dev/ttyUSB0",
        formats=[LineFormat(baudrate=9600)],
        addresses=parse_addresses("1-247"),
    )
    print(report.config_yaml())
"""

from gateway.line.scan.formats import (
    FIRST_ADDRESS,
    LAST_ADDRESS,
    PROBE_MARGIN_S,
    PROBE_REGISTERS,
    PROBE_RESPONSE_S,
    parse_addresses,
    probe_timeout_s,
    scan_formats,
    supported_formats,
)
from gateway.line.scan.identify import (
    DIGILINE,
    DIGILINE_BLOCK,
    REISS,
    REISS_BLOCK,
    REISS_FAMILY,
    TECLINE,
    TECLINE_BLOCK,
    TECLINE_FAMILY,
    UNKNOWN,
)
from gateway.line.scan.probe import IDENTIFY_ATTEMPTS, IDENTIFY_MARGIN_S, Scanner
from gateway.line.scan.report import FoundDevice, ScanReport
from gateway.line.scan.sweep import scan

__all__ = [
    "DIGILINE",
    "DIGILINE_BLOCK",
    "FIRST_ADDRESS",
    "IDENTIFY_ATTEMPTS",
    "IDENTIFY_MARGIN_S",
    "LAST_ADDRESS",
    "PROBE_MARGIN_S",
    "PROBE_REGISTERS",
    "PROBE_RESPONSE_S",
    "REISS",
    "REISS_BLOCK",
    "REISS_FAMILY",
    "TECLINE",
    "TECLINE_BLOCK",
    "TECLINE_FAMILY",
    "UNKNOWN",
    "FoundDevice",
    "ScanReport",
    "Scanner",
    "parse_addresses",
    "probe_timeout_s",
    "scan",
    "scan_formats",
    "supported_formats",
]
