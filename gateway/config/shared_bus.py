"""The ``shared_bus:`` section: other masters reach the sensors through the gateway.

Example::

    shared_bus:
      listen:
        - {host: 127.0.0.1, port: 1502}              # Modbus TCP
        - {host: 127.0.0.1, port: 1503, framing: rtu}  # RTU frames over TCP
      bus_share: 0.25      # of each bus's time, at most
      rate_limit: 50       # requests per second from one address (a burst of a second's worth)
      clients:
        - name: scada
          networks: [10.0.0.0/24]
          cache_max_age: 2.0
        - name: service
          networks: [10.0.1.7/32]
          writes:
            - {device: cl2_basin, registers: ["0x0206-0x020B"]}

Off unless ``listen`` names an address. A device answers to its Modbus address as the unit
id, or to its ``unit_id`` where several buses repeat addresses (checked at load).
"""

from __future__ import annotations

import ipaddress
from enum import StrEnum
from typing import Annotated, Final

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field

MAX_SHARE: Final = 0.9  # the gateway's own polling keeps at least a tenth of every bus
DEFAULT_LISTEN_HOST: Final = "127.0.0.1"
MAX_REGISTER: Final = 0xFFFF

IpNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network
ListenPort = Annotated[int, Field(ge=0, le=65535)]  # 0: any free port (logged, in /healthz)


class _Model(BaseModel):
    # The same as config.model's (which imports this module): declared here, on BaseModel,
    # so ruff still sees pydantic models, whose list defaults are copied per instance.
    model_config = ConfigDict(extra="forbid", frozen=True)


class Framing(StrEnum):
    """How requests travel on the socket."""

    TCP = "tcp"  # Modbus TCP: the MBAP header, no CRC
    RTU = "rtu"  # RTU frames with CRC, as a serial-to-Ethernet converter passes them


class ListenConfig(_Model):
    """One address the gateway serves other masters on."""

    host: Annotated[str, Field(min_length=1)] = DEFAULT_LISTEN_HOST
    port: ListenPort = 502
    framing: Framing = Framing.TCP


def _network(value: object) -> object:
    if isinstance(value, str):
        try:
            return ipaddress.ip_network(value, strict=False)
        except ValueError as exc:
            raise ValueError(f"{value!r} is not an address or network (e.g. 10.0.0.0/24)") from exc
    return value


def _register_range(value: object) -> object:
    """``0x0206``, ``518`` or ``"0x0206-0x020B"`` (inclusive) → ``(first, last)``."""
    if isinstance(value, bool):
        raise ValueError(f"{value!r} is not a register or a range")  # noqa: TRY004 - pydantic
    if isinstance(value, int):
        return (value, value)
    if isinstance(value, str):
        first, _, last = value.partition("-")
        try:
            low = int(first.strip(), 0)
            high = int(last.strip(), 0) if last else low
        except ValueError as exc:
            raise ValueError(
                f"{value!r} is not a register or a range such as '0x0206-0x020B'"
            ) from exc
        return (low, high)
    return value


def _ordered(value: tuple[int, int]) -> tuple[int, int]:
    low, high = value
    if not 0 <= low <= high <= MAX_REGISTER:
        raise ValueError(f"registers {low:#06x}-{high:#06x}: need 0 <= first <= last <= 0xFFFF")
    return value


RegisterRange = Annotated[
    tuple[int, int], BeforeValidator(_register_range), AfterValidator(_ordered)
]


# Requests per second from one source address, whatever they ask (refusals and cache hits
# cost the gateway's process too). 50/s is some ten times what a SCADA polling every
# device of a full line each second sends, and a burst of a second's worth passes at once.
RateLimit = Annotated[float, Field(gt=0, le=10_000)]
DEFAULT_RATE_LIMIT: Final = 50.0


class WriteGrant(_Model):
    """Registers of one device a client may write (all its registers when not listed)."""

    device: Annotated[str, Field(min_length=1)]
    registers: list[RegisterRange] | None = None


class ClientConfig(_Model):
    """A group of other masters, known by where they connect from."""

    name: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[a-z0-9_-]+$")]
    networks: list[Annotated[IpNetwork, BeforeValidator(_network)]] = Field(min_length=1)
    # Reads answered from what the device last sent, if it is at most this old (seconds);
    # None: every read goes to the wire.
    cache_max_age: Annotated[float, Field(gt=0, le=3600)] | None = None
    writes: list[WriteGrant] = []  # none: the client only reads
    # Requests per second from each of its addresses; None: the section's ``rate_limit``.
    rate_limit: RateLimit | None = None


class SharedBusConfig(_Model):
    """Other masters (SCADA, the vendor's software) on the gateway's buses."""

    listen: list[ListenConfig] = []  # empty: off
    # Of each bus's time, at most; divided equally between the source addresses asking
    # (line.fair_share), an address's part between its connections.
    bus_share: Annotated[float, Field(gt=0, le=MAX_SHARE)] = 0.25
    max_wait: Annotated[float, Field(gt=0, le=60)] = 2.0  # seconds, then exception 06
    # Per bus, then exception 06: to the newest request of the address holding the most,
    # if it holds at least two more than the newcomer's, else to the newcomer.
    max_pending: Annotated[int, Field(ge=1, le=1000)] = 16
    max_connections: Annotated[int, Field(ge=1, le=1000)] = 16
    # Requests read from one connection and not yet answered; the socket is read no
    # further meanwhile, so a pipelining client waits in TCP's buffers (backpressure).
    max_in_flight: Annotated[int, Field(ge=1, le=256)] = 16
    rate_limit: RateLimit = DEFAULT_RATE_LIMIT  # per source address; a client may set its own
    idle_timeout: Annotated[float, Field(gt=0, le=86_400)] = 300.0  # a silent connection closes
    clients: list[ClientConfig] = []  # a source not listed reads only, as client "other"

    @property
    def enabled(self) -> bool:
        """Whether the gateway serves other masters at all."""
        return bool(self.listen)
