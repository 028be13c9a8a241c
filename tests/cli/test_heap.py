"""The long-running commands return large freed blocks to the system (glibc's mmap threshold),
and ``gateway run``'s threads allocate from one arena.

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


# A thread's first allocation: in an arena of its own (a new heap, a 64 MiB reservation in the
# process's mappings), unless every thread is held to the main arena.
THREAD_PROBE = """
import ctypes, json, sys, threading
from gateway.cli.heap import one_arena

def reservations():
    heaps = 0
    with open("/proc/self/maps", encoding="utf-8") as maps:
        for line in maps:
            start, end = (int(part, 16) for part in line.split()[0].split("-"))
            heaps += end - start >= 32 * 1024 * 1024 and line.split()[1] == "---p"
    return heaps

took = one_arena() if sys.argv[1] == "one" else None
libc = ctypes.CDLL(None)
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = (ctypes.c_void_p,)
before = reservations()
thread = threading.Thread(target=lambda: libc.free(libc.malloc(1000)))
thread.start()
thread.join()
print(json.dumps({"took": took, "new_heaps": reservations() - before}))
"""


def new_heaps(mode: str) -> tuple[bool | None, int]:
    """Whether one arena took, and the heaps a thread's allocation added."""
    result = subprocess.run(
        [sys.executable, "-c", THREAD_PROBE, mode], capture_output=True, text=True, check=True
    )
    probe = json.loads(result.stdout)
    return probe["took"], int(probe["new_heaps"])


@pytest.mark.skipif(not glibc(), reason="mallopt's arenas are glibc's; elsewhere nothing is set")
def test_threads_allocate_from_one_arena() -> None:
    assert new_heaps("one") == (True, 0)
    # The control: glibc's own behaviour, a heap of its own for the thread.
    _, by_default = new_heaps("default")
    assert by_default >= 1
