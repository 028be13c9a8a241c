"""Who may do what on the shared bus: clients by source address, unit ids, write grants.

Pure: built once from the config, asked for every request.
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Final

from gateway.control.shared_bus.pdu import (
    ILLEGAL_ADDRESS,
    ILLEGAL_FUNCTION,
    RequestRefusedError,
)
from gateway.line.engine.fair_share import Origin

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from gateway.config import GatewayConfig
    from gateway.config.shared_bus import ClientConfig, IpNetwork
    from gateway.control.shared_bus.pdu import ClientRequest

OTHER_CLIENT: Final = "other"  # a source no client lists: it reads, and writes nothing


@dataclass(frozen=True, slots=True, kw_only=True)
class Unit:
    """A device as other masters address it."""

    unit: int
    bus: str
    device: str
    address: int  # its Modbus address on its line


@dataclass(frozen=True, slots=True, kw_only=True)
class ClientPolicy:
    """What one client may do: read (always), from the cache, write where granted; how fast."""

    name: str
    networks: tuple[IpNetwork, ...] = ()
    cache_max_age_s: float | None = None
    rate_limit: float | None = None  # requests/s per source address; None: the section's
    # device -> register ranges (first, last) it may write; None: every register
    writes: Mapping[str, tuple[tuple[int, int], ...] | None] = field(default_factory=dict)

    def matches(self, host: str) -> bool:
        """Whether a connection from ``host`` belongs to this client."""
        address = _address(host)
        return address is not None and any(address in network for network in self.networks)

    def check_write(self, device: str, request: ClientRequest) -> None:
        """Refuse a write this client may not make (:class:`RequestRefusedError`)."""
        if device not in self.writes:
            raise RequestRefusedError(
                ILLEGAL_FUNCTION,
                f"client {self.name} may not write to {device}",
                label="write_not_allowed",
            )
        ranges = self.writes[device]
        if ranges is None:
            return
        for register in range(request.address, request.last + 1):
            if not any(low <= register <= high for low, high in ranges):
                raise RequestRefusedError(
                    ILLEGAL_ADDRESS,
                    f"client {self.name} may not write register {register:#06x} of {device}",
                    label="register_not_allowed",
                )


def _address(host: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    """``host`` as an address, an IPv4 one if it came over IPv6 (``::ffff:10.0.0.7``)."""
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return None
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return address.ipv4_mapped
    return address


def origin_of(peer: tuple[str, int]) -> Origin:
    """The turn a connection's requests go in: its source address, then the connection.

    One machine is one address whether it connects over IPv4 or IPv6-mapped IPv4.
    """
    host, port = peer
    address = _address(host)
    name = str(address) if address is not None else host
    return Origin(address=name, connection=f"{host}:{port}")


def client_policies(clients: Sequence[ClientConfig]) -> tuple[ClientPolicy, ...]:
    """The configured clients, in config order (the first that matches a source wins)."""
    return tuple(
        ClientPolicy(
            name=client.name,
            networks=tuple(client.networks),
            cache_max_age_s=client.cache_max_age,
            rate_limit=client.rate_limit,
            writes={
                grant.device: tuple(grant.registers) if grant.registers is not None else None
                for grant in client.writes
            },
        )
        for client in clients
    )


def client_for(policies: Sequence[ClientPolicy], host: str) -> ClientPolicy:
    """The client a connection from ``host`` belongs to; ``other`` if none lists it."""
    for policy in policies:
        if policy.matches(host):
            return policy
    return ClientPolicy(name=OTHER_CLIENT)


def units(config: GatewayConfig) -> dict[int, Unit]:
    """Every device by the unit id other masters use: its ``unit_id``, else its address."""
    return {
        (unit := device.unit_id if device.unit_id is not None else device.address): Unit(
            unit=unit, bus=device.bus, device=device.name, address=device.address
        )
        for device in config.devices
    }
