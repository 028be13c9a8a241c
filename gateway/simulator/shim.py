"""A pseudo-terminal between a master and a simulated line, with the faults of real adapters.

What users plug in is not a clean pipe: an RS485 adapter without automatic direction
control hears its own transmission (local echo), an FTDI adapter holds received bytes until
its latency timer ticks (16 ms by default on current kernels), a line without biasing or
with a bad earth never falls silent, and a USB adapter can vanish. The shim reproduces each
on a pseudo-terminal pair, so the gateway's handling of them is tested on the real wire
path: the master opens ``path``; the shim relays to the simulator's pty at ``upstream``.

Every fault can be switched while the shim runs (tests flip them between transactions).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import subprocess
import sys
import termios
import tty
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Final

from gateway.errors import GatewayError

if TYPE_CHECKING:
    from pathlib import Path

FTDI_LATENCY_S: Final = 0.016  # ftdi_sio's default latency timer (16 ms; 1 ms with low latency)
NOISE_BYTE: Final = 0xFF  # what an unbiased line reads as between frames: idle-high garbage


class ShimError(GatewayError):
    """The shim cannot open its ends."""


@dataclass
class ShimCounters:
    """What the shim relayed and made up, for tests and benches to assert on."""

    to_line: int = 0  # bytes from the master to the simulated line
    to_master: int = 0  # bytes from the line to the master
    echoed: int = 0
    deliveries: list[float] = field(default_factory=list)  # when held bytes were let go


class LineShim:
    """Relays a master's port to a simulated line, echoing, holding bytes or adding noise.

    Example::

        shim = LineShim(upstream=tmp / "ttySIM", path=tmp / "ttyUSB0", echo=True)
        shim.open()
        ...  # the gateway opens tmp / "ttyUSB0"
        shim.noise_interval_s = 0.001  # a byte of noise every millisecond from now on
        shim.close()
    """

    def __init__(
        self,
        *,
        upstream: Path,
        path: Path,
        echo: bool = False,
        latency_s: float = 0.0,
        noise_interval_s: float = 0.0,
    ) -> None:
        """Describe the shim; :meth:`open` opens both ends (in the running event loop)."""
        self.upstream = upstream
        self.path = path
        self.echo = echo  # the master hears what it sends, before any answer
        self.latency_s = latency_s  # bytes to the master are held until the next tick
        self.counters = ShimCounters()
        self._noise_interval_s = 0.0
        self._loop = asyncio.get_running_loop()
        self._line = -1  # our end of the simulated line
        self._master = -1  # the pty master the gateway's port is the slave of
        self._slave = -1
        self._held = bytearray()
        self._release: asyncio.TimerHandle | None = None
        self._noise: subprocess.Popen[bytes] | None = None
        self.noise_interval_s = noise_interval_s

    # --- faults ------------------------------------------------------------------------

    @property
    def noise_interval_s(self) -> float:
        """A noise byte to the master every this many seconds (0: none)."""
        return self._noise_interval_s

    @noise_interval_s.setter
    def noise_interval_s(self, interval_s: float) -> None:
        self._noise_interval_s = interval_s
        self._stop_noise()
        self._start_noise()

    def _stop_noise(self) -> None:
        if self._noise is not None:
            self._noise.kill()
            self._noise.wait()
            if self._noise.stdout is not None:
                self._noise.stdout.close()
            self._noise = None

    def _start_noise(self) -> None:
        interval_s = self._noise_interval_s
        if interval_s > 0 and self._master >= 0:
            # A process of its own, not the event loop's timers or a thread: timers fire
            # up to a millisecond late and not while the loop is busy, a thread waits for
            # the GIL up to 5 ms; either let silent gaps through that a noisy line has not.
            self._noise = subprocess.Popen(  # noqa: S603 - our own interpreter, fixed code
                [sys.executable, "-c", _NOISE_LOOP, str(self._master), str(interval_s)],
                pass_fds=(self._master,),
                stdout=subprocess.PIPE,
            )

    async def noisy(self) -> None:
        """Return once the noise is on the line (its process takes a while to start)."""
        process = self._noise
        if process is not None and process.stdout is not None:
            await self._loop.run_in_executor(None, process.stdout.readline)

    def drop_carrier(self) -> None:
        """The master's port vanishes, as an unplugged USB adapter's does."""
        self._close_master()

    def restore_carrier(self) -> None:
        """The port comes back at the same path."""
        if self._master < 0:
            self._open_master()

    # --- ends --------------------------------------------------------------------------

    def open(self) -> None:
        """Open the simulated line's pty and make the master's at ``path``."""
        try:
            self._line = os.open(self.upstream, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as exc:
            raise ShimError(f"cannot open {self.upstream}: {exc.strerror}") from exc
        tty.setraw(self._line, termios.TCSANOW)
        self._loop.add_reader(self._line, self._from_line)
        self._open_master()

    def close(self) -> None:
        """Close both ends and remove the link."""
        self.noise_interval_s = 0.0
        if self._release is not None:
            self._release.cancel()
        self._close_master()
        if self._line >= 0:
            self._loop.remove_reader(self._line)
            os.close(self._line)
            self._line = -1

    def _open_master(self) -> None:
        if self.path.is_symlink():
            self.path.unlink()
        master, slave = os.openpty()
        tty.setraw(slave, termios.TCSANOW)
        os.set_blocking(master, False)
        try:
            self.path.symlink_to(os.ttyname(slave))
        except OSError as exc:
            os.close(master)
            os.close(slave)
            raise ShimError(f"cannot create {self.path}: {exc.strerror}") from exc
        self._master, self._slave = master, slave
        self._loop.add_reader(master, self._from_master)
        self._start_noise()

    def _close_master(self) -> None:
        self._stop_noise()  # it holds the master open too
        if self._master >= 0:
            self._loop.remove_reader(self._master)
            os.close(self._master)
            os.close(self._slave)
            self._master = self._slave = -1
        if self.path.is_symlink():
            self.path.unlink()

    # --- relaying ----------------------------------------------------------------------

    def _from_master(self) -> None:
        try:
            data = os.read(self._master, 4096)
        except (BlockingIOError, OSError):
            return  # EIO: the master has the port closed right now
        if not data:
            return
        if self.echo:
            # An adapter without direction control hears each byte as it goes out; on a
            # pty there is no wire time, so the whole request comes back at once.
            self._to_master(data)
            self.counters.echoed += len(data)
        self.counters.to_line += len(data)
        with contextlib.suppress(OSError):
            os.write(self._line, data)

    def _from_line(self) -> None:
        try:
            data = os.read(self._line, 4096)
        except (BlockingIOError, OSError):
            return
        if not data:
            return
        if self.latency_s <= 0:
            self._to_master(data)
            return
        self._held.extend(data)
        if self._release is None:
            # The adapter sends what it holds when its latency timer next expires; the
            # timer runs freely, so the wait is up to one tick, never more.
            now = self._loop.time()
            tick = (now // self.latency_s + 1) * self.latency_s
            self._release = self._loop.call_at(tick, self._let_go)

    def _let_go(self) -> None:
        self._release = None
        data, self._held = bytes(self._held), bytearray()
        self.counters.deliveries.append(self._loop.time())
        self._to_master(data)

    def _to_master(self, data: bytes) -> None:
        if self._master < 0:
            return
        self.counters.to_master += len(data)
        with contextlib.suppress(OSError):
            os.write(self._master, data)


# The noise process: a byte to the master's pty every interval until killed.
_NOISE_LOOP: Final = f"""
import os, sys, time
fd, interval = int(sys.argv[1]), float(sys.argv[2])
try:  # a noisy line does not pause when the machine is busy; root may say so
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
except (OSError, AttributeError):
    pass
written = 0
while True:
    try:
        os.write(fd, bytes([{NOISE_BYTE}]))
    except OSError:
        pass
    written += 1
    if written == 100:  # steady by now: say so
        print("noisy", flush=True)
    time.sleep(interval)
"""
