"""Whether this host's clock can be trusted: the kernel's synchronisation status, and the override.

A Raspberry Pi has no real-time clock: it boots with the last time it saved and an NTP
service steps it later, by hours or days. Until then the wall clock is a guess, and a guess
must not end up in a sensor (``set-clock``, a calibration's date stamp:
:mod:`gateway.control.clock_trust` refuses those). The metrics, ``/healthz`` and the page
show the same status, from here.

The kernel keeps the answer: ``adjtimex(2)`` read with ``modes = 0`` returns the clock's
maximum error, which an NTP service (systemd-timesyncd, chrony, ntpd) keeps small and which
the kernel lets grow by 500 µs a second without one, until it stops at 16 s and the clock
is marked unsynchronised (``STA_UNSYNC``, the call returns ``TIME_ERROR``). ``timedatectl``'s
"System clock synchronized" is that maximum error below 16 s, and so is the verdict here
(:func:`synchronised`): chrony without ``rtcsync`` leaves ``STA_UNSYNC`` set on a clock it
keeps, so the flag alone would say no to a synchronised clock.

The one system call is :func:`read_kernel_clock`, at the edge; the verdict and the status
are pure. :class:`HostClock` puts the two together with the plant's override
(``clock.trust_unsynchronised``) for a plant without time sync.
"""

from __future__ import annotations

import ctypes
import errno
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping

# linux/timex.h and kernel/time/ntp.c: the maximum error the kernel lets a clock reach
# (NTP_PHASE_LIMIT, 16 s in µs); at it, STA_UNSYNC is set and adjtimex returns TIME_ERROR.
MAX_ERROR_LIMIT_US: Final = 16_000_000
STA_UNSYNC: Final = 0x0040
TIME_ERROR: Final = 5
_STATES: Final = ("TIME_OK", "TIME_INS", "TIME_DEL", "TIME_OOP", "TIME_WAIT", "TIME_ERROR")

# The config key's variable (pydantic-settings' form of clock.trust_unsynchronised): the
# command-line commands run without a config file read it too.
TRUST_VARIABLE: Final = "GATEWAY_CLOCK__TRUST_UNSYNCHRONISED"
_TRUE: Final = frozenset({"1", "true", "yes", "on", "y", "t"})  # what pydantic takes as true

FIX: Final = (
    "enable time synchronisation (`timedatectl set-ntp true` for systemd-timesyncd, or "
    'chrony) and wait until `timedatectl` shows "System clock synchronized: yes"; on a '
    "plant without time sync, set this host's clock by hand and set "
    f"clock.trust_unsynchronised: true ({TRUST_VARIABLE}=true)"
)


@dataclass(frozen=True, slots=True, kw_only=True)
class KernelClock:
    """What ``adjtimex(2)`` says of the system clock: its state, status bits and errors."""

    state: int  # TIME_OK (0) ... TIME_ERROR (5)
    status: int  # the STA_* bits
    max_error_us: int
    estimated_error_us: int

    @property
    def state_name(self) -> str:
        """The state's name in linux/timex.h (``TIME_ERROR``)."""
        return _STATES[self.state] if 0 <= self.state < len(_STATES) else str(self.state)


def synchronised(reading: KernelClock) -> bool:
    """Whether the kernel holds the clock synchronised, as ``timedatectl`` says it."""
    return reading.max_error_us < MAX_ERROR_LIMIT_US


@dataclass(frozen=True, slots=True, kw_only=True)
class ClockStatus:
    """The host clock as the gateway trusts it: synchronised, or trusted by the override.

    ``problem`` says why it is not synchronised, in a plant engineer's words ("" when it
    is); the errors are ``None`` when the kernel could not be asked.
    """

    synchronised: bool
    trust_unsynchronised: bool
    max_error_s: float | None
    estimated_error_s: float | None
    kernel_state: str | None
    problem: str

    @property
    def trusted(self) -> bool:
        """Whether the wall clock may be written into a sensor (a date, a stamp)."""
        return self.synchronised or self.trust_unsynchronised

    def as_dict(self) -> dict[str, object]:
        """JSON-ready: ``/healthz``'s and the page's ``clock``."""
        return {
            "synchronized": self.synchronised,
            "trusted": self.trusted,
            "trust_unsynchronised": self.trust_unsynchronised,
            "max_error_s": self.max_error_s,
            "estimated_error_s": self.estimated_error_s,
            "kernel_state": self.kernel_state,
            "problem": self.problem or None,
            "fix": None if self.synchronised else FIX,
        }


def judge(reading: KernelClock | OSError, *, trust_unsynchronised: bool) -> ClockStatus:
    """The status of a reading (or of the failure to take one), with the override."""
    if isinstance(reading, OSError):
        name = errno.errorcode.get(reading.errno or 0, str(reading.errno))
        return ClockStatus(
            synchronised=False,
            trust_unsynchronised=trust_unsynchronised,
            max_error_s=None,
            estimated_error_s=None,
            kernel_state=None,
            problem=f"the kernel's clock status cannot be read (adjtimex: {name}), so "
            "the gateway cannot tell whether the host clock is synchronised",
        )
    max_error_s = reading.max_error_us / 1e6
    ok = synchronised(reading)
    problem = ""
    if not ok:
        problem = (
            f"the kernel holds the host clock unsynchronised ({reading.state_name}, maximum "
            f"error {max_error_s:g} s): no time service has set it, or it lost its servers "
            "hours ago"
        )
    return ClockStatus(
        synchronised=ok,
        trust_unsynchronised=trust_unsynchronised,
        max_error_s=max_error_s,
        estimated_error_s=reading.estimated_error_us / 1e6,
        kernel_state=reading.state_name,
        problem=problem,
    )


def trust_from_environment(environ: Mapping[str, str] | None = None) -> bool:
    """The override as :data:`TRUST_VARIABLE` gives it (where no config file says it)."""
    variables = os.environ if environ is None else environ
    for name, value in variables.items():
        if name.upper() == TRUST_VARIABLE:
            return value.strip().lower() in _TRUE
    return False


# --- the system call, at the edge -------------------------------------------------------------


class _Timeval(ctypes.Structure):
    _fields_ = (("tv_sec", ctypes.c_long), ("tv_usec", ctypes.c_long))


class _Timex(ctypes.Structure):
    """``struct timex`` (adjtimex(2)): longs, as the C library's ``adjtimex`` symbol takes."""

    _fields_ = (
        ("modes", ctypes.c_uint),
        ("offset", ctypes.c_long),
        ("freq", ctypes.c_long),
        ("maxerror", ctypes.c_long),
        ("esterror", ctypes.c_long),
        ("status", ctypes.c_int),
        ("constant", ctypes.c_long),
        ("precision", ctypes.c_long),
        ("tolerance", ctypes.c_long),
        ("time", _Timeval),
        ("tick", ctypes.c_long),
        ("ppsfreq", ctypes.c_long),
        ("jitter", ctypes.c_long),
        ("shift", ctypes.c_int),
        ("stabil", ctypes.c_long),
        ("jitcnt", ctypes.c_long),
        ("calcnt", ctypes.c_long),
        ("errcnt", ctypes.c_long),
        ("stbcnt", ctypes.c_long),
        ("tai", ctypes.c_int),
        ("_reserved", ctypes.c_int * 11),
    )


def _adjtimex() -> Callable[[ctypes.c_void_p], int] | None:
    try:
        call = ctypes.CDLL(None, use_errno=True).adjtimex
    except (OSError, AttributeError):
        return None
    call.argtypes = (ctypes.c_void_p,)
    call.restype = ctypes.c_int
    return call


_ADJTIMEX: Final = _adjtimex()


def read_kernel_clock() -> KernelClock:
    """Ask the kernel (``adjtimex`` with ``modes = 0``: read, change nothing).

    An :class:`OSError` if it cannot be asked (no such call in the C library, or a
    sandbox that forbids it).
    """
    if _ADJTIMEX is None:
        raise OSError(errno.ENOSYS, "adjtimex is not in the C library")
    timex = _Timex()  # zeroed: modes 0
    state = _ADJTIMEX(ctypes.c_void_p(ctypes.addressof(timex)))
    if state < 0:
        code = ctypes.get_errno()
        raise OSError(code, os.strerror(code))
    return KernelClock(
        state=state,
        status=timex.status,
        max_error_us=timex.maxerror,
        estimated_error_us=timex.esterror,
    )


class HostClock:
    """This host's clock as the gateway trusts it: the kernel's word, and the override.

    One per running gateway (the state holds it, the write paths and the shared bus ask
    it); :attr:`trust_unsynchronised` is the config's ``clock.trust_unsynchronised``, set
    again at a reload. Without a config (a command-line command given ``--port``) it is
    :data:`TRUST_VARIABLE`'s. ``read`` is the seam a test gives a reading through.
    """

    def __init__(
        self,
        *,
        trust_unsynchronised: bool | None = None,
        read: Callable[[], KernelClock] = read_kernel_clock,
    ) -> None:
        """The kernel's clock through ``read``; the override given, else the environment's."""
        self.trust_unsynchronised = (
            trust_from_environment() if trust_unsynchronised is None else trust_unsynchronised
        )
        self._read = read

    def status(self) -> ClockStatus:
        """The status now: one system call, no cache (a clock synchronised a second ago is)."""
        try:
            reading: KernelClock | OSError = self._read()
        except OSError as exc:
            reading = exc
        return judge(reading, trust_unsynchronised=self.trust_unsynchronised)
