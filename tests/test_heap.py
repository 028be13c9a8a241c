"""The long-running commands return large freed blocks to the system (glibc's mmap threshold).

Checked in a fresh interpreter, on the C library's own account of its heap (``mallinfo2``):
a large block freed, then a smaller one still large: without the fixed threshold glibc
serves the second from the heap it keeps; with it, from a mapping returned when freed.
"""

from __future__ import annotations

import ctypes
import json
import subprocess
import sys

import pytest

PROBE = """
import ctypes, json, sys
from gateway.cli.heap import return_large_blocks

class Mallinfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
        "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL(None)
libc.mallinfo2.restype = Mallinfo2
took = return_large_blocks() if sys.argv[1] == "fixed" else None
block = bytearray(4 * 1024 * 1024)
del block  # glibc's dynamic threshold would now rise to 4 MiB
before = libc.mallinfo2().arena
block = bytearray(2 * 1024 * 1024)  # above 128 KiB, below 4 MiB
grown = libc.mallinfo2().arena - before
print(json.dumps({"took": took, "heap_grew_by": grown}))
"""


def heap_growth(mode: str) -> tuple[bool | None, int]:
    """Whether the threshold took, and how far the heap grew for the 2 MiB block."""
    result = subprocess.run(
        [sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True
    )
    probe = json.loads(result.stdout)
    return probe["took"], int(probe["heap_grew_by"])


def glibc() -> bool:
    try:
        ctypes.CDLL(None).mallinfo2  # noqa: B018 - glibc 2.33 and later have it
    except (OSError, AttributeError):
        return False
    return True


@pytest.mark.skipif(not glibc(), reason="mallinfo2 is glibc's; elsewhere nothing is set")
def test_large_blocks_come_from_mappings_returned_when_freed() -> None:
    took, grew = heap_growth("fixed")
    assert took is True
    assert grew < 256 * 1024  # the 2 MiB block is a mapping of its own
    # The control: glibc's own behaviour, which the fix is for, puts it in the heap (less
    # whatever free space the heap's top already had).
    _, grew_by_default = heap_growth("default")
    assert grew_by_default >= 1024 * 1024
