"""Local echo: adapters without automatic direction control hear their own transmission.

A two-wire RS485 transceiver whose receiver stays on while it sends (many USB adapters
without automatic direction control, most UART HATs, converters with echo jumpers) hands
every request back to the master before the device's answer. Taken for the answer, the
echo misleads in every way: a read's echoed address bytes become a byte count (a timeout),
its CRC lands in the wrong place (a CRC error), and a function-06 write's echo *is* a valid
06 answer, so a write to an address where nothing answers "succeeds".

The bus's ``echo`` setting says what to expect:

- ``on``: every request comes back first; it is read back and compared byte for byte
  before the answer is looked for. Anything else is an ``echo_mismatch`` (a collision,
  another master on the line, or an adapter that does not echo after all).
- ``off``: no echo is expected. One seen anyway is skipped, counted as ``echo`` and logged
  once with the setting to use.
- ``auto`` (the default): decided from the first reads (a read's echo is never a valid
  answer, so reads tell it apart without doubt), logged once with the setting that fits.

Whatever the setting, the line never accepts an answer that arrived before the request
could have been answered (see :func:`earliest_answer`), so a write cannot succeed on its
echo. This module decides; :mod:`gateway.line.transports.rtu` reads the bytes.
"""

from __future__ import annotations

import logging
from typing import Final

from gateway.config.echo import EchoMode

_LOGGER = logging.getLogger(__name__)

AUTO_DECISION_READS: Final = 3  # agreeing reads before ``auto`` settles
ECHO_MARGIN_S: Final = 0.05  # USB adapters hand received bytes over up to 16 ms late, and more


def earliest_answer(
    sent_at: float,
    *,
    request_bytes: int,
    answer_bytes: int,
    character_s: float,
    turnaround_s: float,
) -> float:
    """The first moment an answer of ``answer_bytes`` can have been received in full.

    The request takes its wire time, the device its turnaround (its minimum response
    time), and the answer its own wire time: what arrives before that is not the answer.
    A master's clock starts before the bytes leave (the adapter adds its own delay), so
    the real answer is always later than this, never earlier.
    """
    return sent_at + (request_bytes + answer_bytes) * character_s + turnaround_s


class EchoPolicy:
    """One bus's expectation of an echo, and what it has seen of one."""

    def __init__(self, *, bus: str, port: str, mode: EchoMode = EchoMode.AUTO) -> None:
        """Start from the configured mode; ``auto`` is undecided until the first reads.

        ``bus`` is the configured bus's name; empty for a port named on the command line,
        whose log lines then speak of the port.
        """
        self.bus = bus or port  # what a log line begins with
        self.setting = f"bus {bus}" if bus else f"the bus on {port} in your config"
        self.port = port
        self.mode = mode
        self.echoes: bool | None = {EchoMode.ON: True, EchoMode.OFF: False}.get(mode)
        self.seen = False  # an echo was seen on this line (in any mode)
        self._votes: list[bool] = []
        self._warned = False

    @property
    def expected(self) -> bool:
        """Whether the next request's echo must be read back before its answer."""
        return self.echoes is True

    def observed_read(self, *, echoed: bool) -> None:
        """``auto``, undecided: a read's answer came after an echo of the request or without.

        (An echo where none is expected is the line's to count: :meth:`unexpected`.)
        """
        if self.echoes is not None:
            return
        self._votes.append(echoed)
        if len(self._votes) < AUTO_DECISION_READS:
            return
        if all(self._votes):
            self.echoes = True
            _LOGGER.info(
                "%s: the adapter on %s echoes every request (local echo); reading it back "
                "before each answer. Set `echo: on` for %s to say so in the config",
                self.bus,
                self.port,
                self.setting,
            )
        elif not any(self._votes):
            self.echoes = False
            _LOGGER.info(
                "%s: the adapter on %s does not echo what it sends; set `echo: off` for "
                "%s to say so in the config",
                self.bus,
                self.port,
                self.setting,
            )
        else:  # mixed: another master or noise; keep looking at fresh reads
            self._votes.clear()

    def unexpected(self) -> None:
        """An echo was seen although the bus is set to ``echo: off``: said once."""
        self.seen = True
        if self._warned:
            return
        self._warned = True
        _LOGGER.warning(
            "%s: the adapter on %s echoes every request back (its receiver stays on while it "
            "sends) but %s has `echo: off`; set `echo: on` (or `auto`) for it. Until "
            "then echoes are skipped and counted as errors of kind echo",
            self.bus,
            self.port,
            self.setting,
        )
