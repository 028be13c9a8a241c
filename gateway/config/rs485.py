"""A bus's ``rs485:`` block: the kernel's RS485 mode for a UART that switches its driver by RTS.

On-board UARTs and RS485 HATs whose transceiver direction follows RTS need the kernel to
raise RTS while it sends and drop it after the last stop bit (``TIOCSRS485``, the kernel's
Documentation/driver-api/serial/serial-rs485.rst). USB adapters with automatic direction
control need nothing, and most of their drivers refuse the mode. Example::

    buses:
      - name: line1
        port: /dev/ttyAMA0
        rs485: {rts_level_for_tx: true, rts_level_for_rx: false, delay_before_tx_ms: 0}

Delays are whole milliseconds, as ``struct serial_rs485`` carries them
(``delay_rts_before_send``, ``delay_rts_after_send``).
"""

from __future__ import annotations

from typing import Annotated, Final

from pydantic import BaseModel, ConfigDict, Field

# serial_core.c clamps both RTS delays to RS485_MAX_RTS_DELAY (100 ms) since Linux 6.0;
# a longer one is a typo, not a transceiver's need.
MAX_RTS_DELAY_MS: Final = 100

RtsDelayMs = Annotated[int, Field(ge=0, le=MAX_RTS_DELAY_MS)]


class Rs485Config(BaseModel):
    """The kernel's RS485 mode of one serial port (``struct serial_rs485``).

    ``rts_level_for_tx`` is the RTS level while sending (``SER_RS485_RTS_ON_SEND``: true
    for the usual transceiver whose DE pin is active high), ``rts_level_for_rx`` the level
    after sending, while receiving (``SER_RS485_RTS_AFTER_SEND``). ``rx_during_tx`` keeps
    the receiver on while sending (``SER_RS485_RX_DURING_TX``, pyserial's ``loopback``):
    the gateway then hears its own request as an echo (the bus's ``echo: on``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    rts_level_for_tx: bool = True
    rts_level_for_rx: bool = False
    delay_before_tx_ms: RtsDelayMs = 0  # RTS set, then this wait, then the first bit
    delay_before_rx_ms: RtsDelayMs = 0  # the last stop bit, then this wait, then RTS back
    rx_during_tx: bool = False
