"""The line of a bus, picked from its port: serial, RTU over TCP, or Modbus TCP.

Every place that opens a bus (the gateway, the command line's reads and writes, the scan)
builds its line here, so a ``tcp://`` port is a Modbus TCP session wherever a port can be
given, and a ``socket://`` one keeps its session watched.
"""

from __future__ import annotations

from typing import TYPE_CHECKING
from urllib.parse import urlsplit

from gateway.config.echo import EchoMode
from gateway.config.network import DEFAULT_TCP, MBAP_URL_SCHEME, RTU_OVER_TCP_SCHEME
from gateway.line.transports.serial_line import SerialLine

if TYPE_CHECKING:
    from gateway.config.network import TcpSettings
    from gateway.line.boundary import Line
    from gateway.line.stats import LineStats
    from gateway.line.transports.port_access import PortOptions
    from gateway.wire.timing import LineFormat


def build_line(
    *,
    port: str,
    line: LineFormat,
    stats: LineStats | None = None,
    tcp: TcpSettings | None = None,
    bus: str = "",
    echo: EchoMode = EchoMode.AUTO,
    options: PortOptions | None = None,
) -> Line:
    """The :class:`~gateway.line.boundary.Line` for ``port``: ``tcp://``, ``socket://`` or serial.

    ``tcp`` (the bus's ``tcp:`` settings; ``None``: the defaults) applies to the two network
    kinds; the config refuses it on any other port. ``echo`` applies to what carries RTU
    (a serial port, ``socket://``), ``options`` (exclusive opening, RS485 mode) to a serial
    port. ``bus`` names the line in log lines. Example::

        build_line(port="tcp://10.0.0.5:502", line=LineFormat(baudrate=19200, parity="E"))
    """
    scheme = urlsplit(port).scheme if "://" in port else ""
    settings = tcp if tcp is not None else DEFAULT_TCP
    # The network kinds are imported when a port names one: a serial plant keeps none of them.
    if scheme == MBAP_URL_SCHEME:
        from gateway.line.transports.modbus_tcp import ModbusTcpLine  # noqa: PLC0415

        return ModbusTcpLine(port=port, line=line, stats=stats, tcp=settings, bus=bus)
    if scheme == RTU_OVER_TCP_SCHEME:
        from gateway.line.transports.rtu_over_tcp import RtuOverTcpLine  # noqa: PLC0415

        return RtuOverTcpLine(port=port, line=line, stats=stats, tcp=settings, bus=bus, echo=echo)
    return SerialLine(port=port, line=line, stats=stats, bus=bus, echo=echo, options=options)
