"""Line timing of Modbus RTU, shared by the bus owner and the simulator's referee.

Constants carry their source. Everything here is pure arithmetic on the line format.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Literal

Parity = Literal["N", "E", "O"]

# S10 manual 5.1, H10/H20 manual 5.1, tecLine manual 3.1: a character is 10 bits for
# 8N1 and 11 bits for every other format (8E1, 8O1, 8N2).
BITS_8N1: Final = 10
BITS_OTHER: Final = 11
FRAME_GAP_CHARACTERS: Final = 3.5  # t2 / "end identifier": 3.5 character times
DIGILINE_MIN_GAP_S: Final = 0.002  # S10 manual 5.1 t2: "3.5 characters or at least 2 ms"
TYPICAL_PROCESSING_S: Final = 0.005  # S10 manual 5.1 t1: typically 5 ms


@dataclass(frozen=True, slots=True, kw_only=True)
class LineFormat:
    """Baud rate and character format of one RS485 line.

    Example::

        LineFormat(baudrate=9600, parity="E", stopbits=1)
    """

    baudrate: int = 9600
    parity: Parity = "N"
    stopbits: int = 1

    @property
    def bits_per_character(self) -> int:
        """Bits on the wire per byte: start, 8 data, parity and stop bits."""
        return BITS_8N1 if (self.parity, self.stopbits) == ("N", 1) else BITS_OTHER

    @property
    def character_s(self) -> float:
        """Time one character takes on the wire."""
        return self.bits_per_character / self.baudrate

    def wire_s(self, nbytes: int) -> float:
        """Time ``nbytes`` take on the wire, back to back."""
        return nbytes * self.character_s

    def frame_gap_s(self, min_gap_s: float = 0.0) -> float:
        """Silence required between frames: 3.5 characters, or a device's larger minimum."""
        return max(FRAME_GAP_CHARACTERS * self.character_s, min_gap_s)

    def __str__(self) -> str:
        """``9600 8E1`` style, as plant engineers write it."""
        return f"{self.baudrate} 8{self.parity}{self.stopbits}"
