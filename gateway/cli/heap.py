"""How the long-running commands (``run``, ``demo``) ask the C library to manage the heap.

glibc serves a block of 128 KiB or more from a mapping of its own, returned to the system
when freed, until the first such block is freed: from then on it raises that threshold to
the block's size (up to 32 MiB) and serves large blocks from the heap, which it keeps. A
gateway builds large blocks now and then and keeps few: a scrape of ``/metrics`` at 16 x 16
devices is some 6 MB of text built a family at a time, the start's first read of every
point a burst of thousands of messages, and the heap keeps what they took (at 16 x 16,
``bench/publish.py``, three runs each: 93-96 MiB after a scrape, 85-90 with the threshold
fixed). Setting the threshold with ``mallopt`` fixes it at 128 KiB. Python's own small
objects are not concerned (its allocator takes arenas of its own).

glibc also gives each thread that allocates an arena of its own (up to eight a core),
each a heap of its own that keeps its free pages. A running gateway's helper threads (the
disk queue's checkpoints, the metrics server, the port opener) allocate little and seldom,
and a plain run kept some 0.35 MiB in their arenas (``bench/memory.py --reference``). So
``gateway run`` asks for one arena for every thread (``M_ARENA_MAX``, as
``MALLOC_ARENA_MAX=1`` in the environment): they allocate from the main one, under its
lock, which they take a few times a second (the demo, with its simulators, keeps glibc's).

Where the C library is not glibc (musl has no ``mallopt``), nothing changes.
"""

from __future__ import annotations

import ctypes
from typing import Final

M_MMAP_THRESHOLD: Final = -3  # malloc.h
M_ARENA_MAX: Final = -8  # malloc.h
LARGE_BLOCK_BYTES: Final = 128 * 1024  # glibc's default threshold, kept from now on
ARENAS: Final = 1  # the main arena, for every thread


def _mallopt(option: int, value: int) -> bool:
    """The C library's ``mallopt``; whether it took (``False`` where it is not glibc)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(option, value) == 1)


def return_large_blocks() -> bool:
    """Fix the C library's mmap threshold; whether it took (``False`` on other C libraries)."""
    return _mallopt(M_MMAP_THRESHOLD, LARGE_BLOCK_BYTES)


def one_arena() -> bool:
    """Every thread allocates from the main arena; whether it took. Call it before threads."""
    return _mallopt(M_ARENA_MAX, ARENAS)
