"""A configured bus's port, as the line opens it and as ``check-config`` judges its name.

The line knows how to open a device and why one does not open; what this plant configured
is the config's. This module joins the two above the line, so the line floor takes plain
options and never reads the config's models: a bus's ``rs485:`` block and the gateway's
``shared_bus.listen`` addresses (offered in the message of a port in use, since another
master on the line would corrupt its frames) become :class:`PortOptions`, and every bus's
port name is checked for a kernel-numbered ``/dev/ttyUSBn`` that can swap at a replug.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from gateway.line.transports.port_access import PortOptions
from gateway.line.transports.port_names import port_name_advice

if TYPE_CHECKING:
    from collections.abc import Iterator

    from gateway.config.model import BusConfig, GatewayConfig
    from gateway.config.problems import KeyPath
    from gateway.config.shared_bus import SharedBusConfig
    from gateway.line.transports.port_names import SystemRoots


def port_options(bus: BusConfig, shared: SharedBusConfig) -> PortOptions:
    """A configured bus's options: its RS485 mode, and where the shared bus listens."""
    hints = []
    for listen in shared.listen:
        host = "127.0.0.1" if listen.host in {"0.0.0.0", "::"} else listen.host  # noqa: S104
        if listen.port == 0:  # any free port: the running gateway says which
            hints.append(f"{host}, the port its /healthz shows under shared_bus.listening")
        elif listen.framing == "rtu":
            hints.append(
                f"RTU over TCP at {host}:{listen.port} "
                f"(`gateway read --port socket://{host}:{listen.port} ...`)"
            )
        else:
            hints.append(f"Modbus TCP at {host}:{listen.port} (unit id: the device's address)")
    return PortOptions(rs485=bus.rs485, shared_bus=tuple(hints))


def port_advice(config: GatewayConfig, roots: SystemRoots) -> Iterator[tuple[KeyPath, str]]:
    """``check-config``'s warnings about the ports of a valid config, by key path."""
    for index, bus in enumerate(config.buses):
        advice = port_name_advice(bus.port, roots)
        if advice is not None:
            yield ("buses", index, "port"), advice
