"""The registers each device last sent, with when: reads of other masters answered without the wire.

A shared-bus client may accept an answer of a given age (``cache_max_age``); a read whose
every register the device sent within that age is answered from here, saving bus time.
Only what a device itself answered is kept, so an answer built from it is the answer the
device gave; a write to a register (the gateway's or another master's) forgets it, since
the device may hold something else now.

Kept only when some client may be answered from it: at 16 x 16 devices it holds some
tens of thousands of registers.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Sequence


class RegisterCache:
    """The last registers of every device of one line, by device name and address."""

    def __init__(self, *, enabled: bool = False) -> None:
        """An empty cache; while not ``enabled`` it keeps nothing and answers nothing."""
        self.enabled = enabled
        self._words: dict[str, dict[int, tuple[int, float]]] = {}

    def store(self, device: str, address: int, registers: Sequence[int], at: float) -> None:
        """Keep registers the device answered at monotonic time ``at``."""
        if not self.enabled:
            return
        words = self._words.setdefault(device, {})
        for offset, value in enumerate(registers):
            words[address + offset] = (value, at)

    def drop(self, device: str) -> None:
        """Drop every register of a device (a reload removed or re-planned it)."""
        self._words.pop(device, None)

    def forget(self, device: str, address: int, count: int) -> None:
        """Drop registers a write may have changed."""
        words = self._words.get(device)
        if not words:
            return
        for register in range(address, address + count):
            words.pop(register, None)

    def lookup(
        self, device: str, address: int, count: int, *, not_before: float
    ) -> tuple[int, ...] | None:
        """The registers if every one was answered at ``not_before`` or later, else ``None``."""
        words = self._words.get(device)
        if not self.enabled or not words:
            return None
        found = []
        for register in range(address, address + count):
            entry = words.get(register)
            if entry is None or entry[1] < not_before:
                return None
            found.append(entry[0])
        return tuple(found)
