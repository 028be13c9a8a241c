"""A bus's ``echo`` setting: what its adapter does with what it sends.

A two-wire RS485 adapter without automatic direction control hears its own transmission:
every request comes back before its answer. The setting is read once, here, into an
:class:`EchoMode` that the line (:mod:`gateway.line.transports.echo`) acts on.
"""

from __future__ import annotations

from enum import StrEnum


class EchoMode(StrEnum):
    """What the bus's adapter does with what it sends.

    ``on``: every request is read back before its answer; ``off``: none is expected;
    ``auto``: decided from the first reads, and the setting that fits is logged.
    """

    OFF = "off"
    ON = "on"
    AUTO = "auto"


def echo_words(value: object) -> object:
    """YAML 1.1 reads a bare ``off``/``on`` as false/true: take them as the words meant."""
    if value is True:
        return EchoMode.ON.value
    if value is False:
        return EchoMode.OFF.value
    return value
