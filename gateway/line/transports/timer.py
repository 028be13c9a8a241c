"""A wait that ends within tens of microseconds of a monotonic deadline, without a busy loop.

asyncio's timers end up to 1 ms late: the selector loop hands epoll its timeout in whole
milliseconds, rounded up (``selectors.EpollSelector.select``), so a 0.3 ms gap at 115200
baud became 1 ms and the line stood idle for the rest. A Linux ``timerfd`` armed at the
deadline on ``CLOCK_MONOTONIC`` (the clock of :func:`time.monotonic`) is no epoll timeout
but a file descriptor that becomes readable: the kernel's high-resolution timer wakes the
loop when the deadline is due, and the loop thread sleeps until then (no spin, no blocking
``time.sleep`` that would hold up the other lines of the same loop).

Python 3.11 and 3.12 have no ``os.timerfd_create`` (3.13 has), so the three calls go
through ``ctypes`` to the C library. Where there is none (not Linux, or a loop without
``add_reader``), the wait falls back to :func:`asyncio.sleep` and ends up to 1 ms late:
late is safe for every timing rule, only slower.
"""

from __future__ import annotations

import asyncio
import ctypes
import os
import sys
import time
from typing import Final

CLOCK_MONOTONIC: Final = 1  # linux/time.h; the clock of time.monotonic() on Linux
TFD_TIMER_ABSTIME: Final = 1  # linux/timerfd.h: it_value is a point in time, not a delay


class _Timespec(ctypes.Structure):
    _fields_ = (("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long))


class _Itimerspec(ctypes.Structure):
    _fields_ = (("it_interval", _Timespec), ("it_value", _Timespec))


def _libc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.timerfd_create.argtypes = (ctypes.c_int, ctypes.c_int)
        libc.timerfd_settime.argtypes = (
            ctypes.c_int,
            ctypes.c_int,
            ctypes.POINTER(_Itimerspec),
            ctypes.c_void_p,
        )
    except (OSError, AttributeError):
        return None
    return libc


_LIBC: Final = _libc()


class DeadlineTimer:
    """Sleeps until a :func:`time.monotonic` deadline; one waiter at a time (the bus task)."""

    def __init__(self) -> None:
        """No file descriptor until the first wait."""
        self._fd: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._waiter: asyncio.Future[None] | None = None
        self._spec = _Itimerspec()
        self._usable = _LIBC is not None

    async def sleep_until(
        self, deadline: float, loop: asyncio.AbstractEventLoop | None = None
    ) -> bool:
        """Return at ``deadline`` (monotonic seconds), or at once if it has passed.

        ``loop`` is the running loop where the caller knows it: asking for it costs a
        system call (``getpid``, asyncio's check for a fork), dear on a virtual machine.

        Returns whether the timer woke the wait: then the event loop looked at every
        descriptor it watches at or after ``deadline`` and, in the same pass, before this
        returns, handed over what any of them had to read (a port's bytes). ``False`` when
        the deadline had passed or the fallback slept.
        """
        if deadline <= time.monotonic():
            return False
        if loop is None:
            loop = asyncio.get_running_loop()
        if self._waiter is not None or not (
            # The timer of this loop set at once: _arm()'s call only where one is to be opened.
            self._set(deadline) if self._loop is loop else self._arm(loop, deadline)
        ):
            await asyncio.sleep(deadline - time.monotonic())
            return False
        waiter = loop.create_future()
        self._waiter = waiter
        try:
            await waiter
        finally:
            self._waiter = None
            if not waiter.done():  # cancelled: the timer must not fire for nobody
                self._set(0.0)
        return True

    def close(self) -> None:
        """Release the file descriptor (idempotent); the next wait makes a new one."""
        fd, loop, self._fd, self._loop = self._fd, self._loop, None, None
        if fd is None:
            return
        if loop is not None and not loop.is_closed():
            loop.remove_reader(fd)
        os.close(fd)

    def _arm(self, loop: asyncio.AbstractEventLoop, deadline: float) -> bool:
        """Set the timer to fire at ``deadline``; ``False`` where no timerfd can be used."""
        if not self._usable:
            return False
        if self._loop is not loop:
            self.close()
            try:
                self._open(loop)
            except (OSError, NotImplementedError):
                self._usable = False  # the fallback from now on: late, never wrong
                self.close()
                return False
        return self._set(deadline)

    def _open(self, loop: asyncio.AbstractEventLoop) -> None:
        assert _LIBC is not None  # noqa: S101 - _usable says so
        fd = _LIBC.timerfd_create(CLOCK_MONOTONIC, os.O_NONBLOCK | os.O_CLOEXEC)
        if fd < 0:
            raise OSError(ctypes.get_errno(), "timerfd_create failed")
        self._fd = fd
        loop.add_reader(fd, self._fired)
        self._loop = loop

    def _set(self, deadline: float) -> bool:
        """Arm at ``deadline``, or disarm with ``0.0``."""
        if self._fd is None or _LIBC is None:
            return False
        value = self._spec.it_value
        if deadline > 0:
            seconds = int(deadline)
            value.tv_sec, value.tv_nsec = seconds, max(1, int((deadline - seconds) * 1e9))
        else:
            value.tv_sec = value.tv_nsec = 0
        return bool(_LIBC.timerfd_settime(self._fd, TFD_TIMER_ABSTIME, self._spec, None) == 0)

    def _fired(self) -> None:
        assert self._fd is not None  # noqa: S101 - the reader goes with the descriptor
        try:  # noqa: SIM105 - contextlib.suppress: three calls more on every transaction
            os.read(self._fd, 8)  # the expiration count, to clear readiness
        except BlockingIOError:  # disarmed just before: nothing to read
            pass
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)
