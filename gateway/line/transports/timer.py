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

While a bus worker polls, the line's timer is also the event loop watch's look
(:meth:`DeadlineTimer.look`): every firing tells the watch how late the loop ran it, an
answer's wait is woken by it (:meth:`DeadlineTimer.wake`) no later than one look after it
began, and a firing that wakes nobody sets it one look ahead again. The loop's lateness is
so measured with no timer of asyncio's in a transaction: the watch's own tick and the
answer's timeout were two per transaction, with their cancels, some 30 of its 305 calls.
"""

from __future__ import annotations

import asyncio
import ctypes
import os
import sys
import time
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from gateway.line.boundary import WaitWatch

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
        self._armed = 0.0  # the deadline the timer is set to; 0.0 disarmed
        self._watch: WaitWatch | None = None  # while the timer looks for it (look() to rest())

    def look(self, watch: WaitWatch | None) -> None:
        """Be ``watch``'s look until :meth:`rest`: the watch counts the worker as asleep.

        Every firing from now on tells ``watch`` how late it ran, and one that wakes
        nobody (the worker busy with other work) sets the timer ``watch.look_s`` ahead
        again. Where no timerfd can be used, the timer does not look, and the watch's own
        tick keeps time. Nothing changes if it looks already, or ``watch`` is None.
        """
        if watch is not None and self._watch is None and self._usable:
            self._watch = watch
            watch.asleep()

    def rest(self) -> None:
        """Stop looking (the worker sleeps on a timer of its own, or stops); disarmed."""
        watch, self._watch = self._watch, None
        if watch is None:
            return
        if self._armed:
            self._set(0.0)
        now = time.monotonic()
        watch.awake(now, now)  # not late: the watch's tick takes over, if anyone is awake

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
        now = time.monotonic()
        if deadline <= now:
            return False
        if loop is None:
            loop = asyncio.get_running_loop()
        if self._waiter is not None or not self._rearm(loop, deadline, now):
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

    def wake(self, waiter: asyncio.Future[None], deadline: float, now: float) -> bool:
        """Resolve ``waiter`` at ``deadline``, unless something resolves it first.

        An inbox's wait for bytes: while the timer looks, no later than one look from
        ``now``, and it stays set when the bytes come first (it looks on over what the
        worker does next, and the next wait sets it anew). ``False`` where no timerfd can be
        used, or another wait holds the timer: the caller sets a timer of the loop.
        """
        if self._waiter is not None or not self._usable:
            return False
        watch = self._watch
        if watch is not None:
            look_at = now + watch.look_s
            if look_at < deadline:  # noqa: PLR1730 - min() is a call more on every answer
                deadline = look_at
        if not self._rearm(waiter.get_loop(), deadline, now):
            return False
        self._waiter = waiter
        return True

    def unwake(self, waiter: asyncio.Future[None]) -> None:
        """The wait of :meth:`wake` ended; the timer is disarmed unless it looks."""
        if self._waiter is waiter:
            self._waiter = None
            if self._watch is None and self._armed:
                self._set(0.0)

    def close(self) -> None:
        """Stop looking and release the file descriptor (idempotent); a wait makes a new one."""
        self.rest()
        self._release()

    def _release(self) -> None:
        waiter = self._waiter
        if waiter is not None and not waiter.done():  # its wait ends: the line is closed
            waiter.set_result(None)
        fd, loop, self._fd, self._loop = self._fd, self._loop, None, None
        self._armed = 0.0
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
            self._release()  # of another loop, if any: a look goes on, on this one
            try:
                self._open(loop)
            except (OSError, NotImplementedError):
                self._usable = False  # the fallback from now on: late, never wrong
                self.close()  # no look either: the watch's tick keeps time
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
        self._armed = deadline
        value = self._spec.it_value
        if deadline > 0:
            seconds = int(deadline)
            value.tv_sec, value.tv_nsec = seconds, max(1, int((deadline - seconds) * 1e9))
        else:
            value.tv_sec = value.tv_nsec = 0
        return bool(_LIBC.timerfd_settime(self._fd, TFD_TIMER_ABSTIME, self._spec, None) == 0)

    def _rearm(self, loop: asyncio.AbstractEventLoop, deadline: float, now: float) -> bool:
        """Set for a wait's ``deadline`` on ``loop``: at once on its timer, opened if need be.

        Set anew past its last deadline, the timer's firing was not handed over yet: the
        loop was held (the worker's own code ran on: a sink that computes, a poll straight
        after it). Setting it clears that firing, so the watch it looks for is told here
        how late it is, as the firing would have said.
        """
        watch = self._watch
        if watch is not None and 0 < self._armed < now:
            watch.late(self._armed, now)
        return self._set(deadline) if self._loop is loop else self._arm(loop, deadline)

    def _fired(self) -> None:
        assert self._fd is not None  # noqa: S101 - the reader goes with the descriptor
        try:
            os.read(self._fd, 8)  # the expiration count, to clear readiness
        except BlockingIOError:  # set anew since it fired, in this pass: not due yet
            return
        due, self._armed = self._armed, 0.0
        waiter = self._waiter
        watch = self._watch
        if watch is not None:
            now = time.monotonic()
            watch.late(due, now)
            if waiter is None or waiter.done():  # nobody waits: look again, one look on
                self._set(now + watch.look_s)
        if waiter is not None and not waiter.done():
            waiter.set_result(None)
