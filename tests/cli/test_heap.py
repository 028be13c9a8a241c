"""The long-running commands return large freed blocks to the system (glibc's mmap threshold).

Checked in a fresh interpreter, on the C library's own account (``mallinfo2``): a large
block freed, then a smaller one still large: without the fixed threshold glibc serves the
second from the heap it keeps; with it, from a mapping of its own, returned when freed.
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
before = libc.mallinfo2()
block = bytearray(2 * 1024 * 1024)  # above 128 KiB, below 4 MiB
after = libc.mallinfo2()
print(json.dumps({
    "took": took,
    "mapped": after.hblkhd - before.hblkhd,  # in mappings of their own
    "heap": after.uordblks - before.uordblks,  # in the heap
}))
"""


def where_it_went(mode: str) -> tuple[bool | None, int, int]:
    """Whether the threshold took, and the 2 MiB block's bytes: mapped apart, in the heap."""
    result = subprocess.run(
        [sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True
    )
    probe = json.loads(result.stdout)
    return probe["took"], int(probe["mapped"]), int(probe["heap"])


def glibc() -> bool:
    try:
        ctypes.CDLL(None).mallinfo2  # noqa: B018 - glibc 2.33 and later have it
    except (OSError, AttributeError):
        return False
    return True


BLOCK = 2 * 1024 * 1024


@pytest.mark.skipif(not glibc(), reason="mallinfo2 is glibc's; elsewhere nothing is set")
def test_large_blocks_come_from_mappings_returned_when_freed() -> None:
    took, mapped, heap = where_it_went("fixed")
    assert took is True
    assert mapped >= BLOCK  # a mapping of its own, returned when freed
    assert heap < BLOCK
    # The control: glibc's own behaviour, which the fix is for, serves it from the heap.
    _, mapped_by_default, heap_by_default = where_it_went("default")
    assert heap_by_default >= BLOCK
    assert mapped_by_default < BLOCK
