"""The ``buses[].tcp:`` section: how the gateway keeps a session with a serial device server.

A converter on the network (RTU over TCP, ``socket://``, or Modbus TCP, ``tcp://``) can
vanish without a word: powered off, a cable pulled, a firewall that forgets the
connection. The kernel would keep such a session for hours; these settings end it within a
bounded time (TCP keepalive while idle, a user timeout while requests go unacknowledged),
and one whose peer stays connected but answers nothing after a number of requests in a
row. Example::

    buses:
      - name: hall
        port: tcp://10.0.0.5:502
        tcp: {keepalive_s: 10, user_timeout_s: 20, connect_pause_s: 0.5}
"""

from __future__ import annotations

from typing import Annotated, Final
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo

MBAP_URL_SCHEME: Final = "tcp"  # tcp://host:port: a converter in Modbus TCP mode (MBAP)
RTU_OVER_TCP_SCHEME: Final = "socket"  # pyserial's socket:// URL: RTU frames over TCP
TCP_SCHEMES: Final = frozenset({MBAP_URL_SCHEME, RTU_OVER_TCP_SCHEME})


class TcpSettings(BaseModel):
    """Session settings of a ``socket://`` or ``tcp://`` bus; every one has a default.

    A vanished peer ends the session after ``user_timeout_s`` while requests are sent (the
    kernel's TCP_USER_TIMEOUT: data unacknowledged for that long), and at the first
    keepalive probe (after ``keepalive_s`` idle, then every ``keepalive_interval_s``) past
    ``user_timeout_s`` while the line is idle: Linux lets the user timeout stand for the
    probe count (tcp(7)), which counts only with ``user_timeout_s: 0`` (the kernel's
    default, some 15 minutes of retransmissions while busy). A peer that acknowledges but
    never answers ends it after ``silent_requests`` requests in a row without a byte back.
    The bus is then reopened on its backoff.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    connect_timeout_s: Annotated[float, Field(gt=0, le=60)] = 5.0
    # Many converters drop the first request sent right after a connection is accepted.
    connect_pause_s: Annotated[float, Field(ge=0, le=10)] = 0.0
    keepalive_s: Annotated[int, Field(ge=1, le=3600)] = 10  # TCP_KEEPIDLE
    keepalive_interval_s: Annotated[int, Field(ge=1, le=600)] = 5  # TCP_KEEPINTVL
    keepalive_count: Annotated[int, Field(ge=1, le=20)] = 3  # TCP_KEEPCNT
    user_timeout_s: Annotated[float, Field(ge=0, le=3600)] = 20.0  # TCP_USER_TIMEOUT; 0: off
    # Requests in a row that get no byte back before the session is closed and reopened;
    # 0: never. A converter in Modbus TCP mode answers 0B for a silent device, so silence
    # there is the session's; over RTU over TCP it may also be every device being away.
    silent_requests: Annotated[int, Field(ge=0, le=1000)] = 5
    # The least time between an answer and the next request: no inter-frame gap is kept
    # on a tcp:// socket (the converter keeps it on its serial side), so a converter that
    # needs a breath between requests gets it here.
    request_pause_ms: Annotated[float, Field(ge=0, le=1000)] = 0.0


DEFAULT_TCP: Final = TcpSettings()


def tcp_for_network_port(value: TcpSettings | None, info: ValidationInfo) -> TcpSettings | None:
    """``tcp:`` belongs to a ``socket://`` or ``tcp://`` port; on a serial port it is a mistake.

    A setting that would do nothing is refused rather than ignored: whoever wrote it
    believes the bus is on the network.
    """
    port = info.data.get("port")
    if value is None or not isinstance(port, str):
        return value  # nothing set, or the port is wrong and says so itself
    if urlsplit(port).scheme not in TCP_SCHEMES if "://" in port else True:
        raise ValueError(
            f"the tcp settings apply to socket:// and tcp:// ports only, not to {port}; "
            "remove them or give the converter's URL"
        )
    return value
