"""Why a serial port is not open, in words that name the remedy.

A port that cannot be opened is a plant engineer's problem, not the gateway's, so the
driver's errno is turned into a :class:`PortReason` (what ``/healthz``, the metrics and the
log name) and a message that says what to do: the ``/dev/serial/by-id`` names that do exist
when the port is missing, the group to join when permission is denied (with the user, the
node's owner, group and mode), the process that holds a port in use, or the driver's own
error.

Who holds a port is read from ``/proc``: the advisory locks (``/proc/locks``, proc(5)), the
holder's command line, and the systemd service it runs in (its cgroup, cgroups(7)), so the
message can say which unit to stop. ``EBUSY`` with no lock holder is the kernel's exclusive
mode (``TIOCEXCL``) set by a program that takes no lock, or left by one that ended while
another still has the port open. Two masters on one line corrupt each other's frames, so
the message offers the running gateway's shared bus instead, where it listens.
"""

from __future__ import annotations

import errno
import grp
import os
import pwd
import stat
from enum import StrEnum
from typing import TYPE_CHECKING, Final

from gateway.errors import PortUnavailableError
from gateway.line.transports.port_names import connected_adapters

if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.line.transports.port_names import SystemRoots

SERVICE_UNIT: Final = "rs485-gateway"  # deploy/systemd/rs485-gateway.service


class PortReason(StrEnum):
    """Why a port is not open: what ``/healthz``, the metrics and the log name."""

    MISSING = "missing"  # no such device node: unplugged, renamed, or a typo
    PERMISSION = "permission_denied"  # the user is not in the device's group
    IN_USE = "in_use"  # another master holds it (the lock, or TIOCEXCL)
    NO_RS485 = "no_rs485_mode"  # rs485: configured, the driver has no TIOCSRS485
    DRIVER = "driver_error"  # anything else the driver said


def strerror(exc: BaseException) -> str:
    """An error's text as the system says it (``Permission denied``), else its message."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc)


def _errno(exc: BaseException) -> int | None:
    """The errno of an open failure: pyserial keeps it as its first argument."""
    if isinstance(exc, OSError) and exc.errno is not None:
        return exc.errno
    first = exc.args[0] if exc.args else None
    return first if isinstance(first, int) else None


def port_unavailable(
    port: str, exc: BaseException, *, roots: SystemRoots, shared_bus: Sequence[str] = ()
) -> PortUnavailableError:
    """The error for a port that failed to open with ``exc``: its reason and its remedy.

    ``shared_bus``: how other programs reach the line through the gateway that owns it
    (``shared_bus.listen``), offered when the port is in use.
    """
    code = _errno(exc)
    if code == errno.ENOENT or (code is None and not roots.node(port).exists()):
        return PortUnavailableError(
            f"cannot open {port}: it does not exist; {connected_adapters(roots)}",
            port=port,
            reason=PortReason.MISSING,
        )
    if code in {errno.EACCES, errno.EPERM}:
        return PortUnavailableError(
            _permission_text(port, roots), port=port, reason=PortReason.PERMISSION
        )
    if code in {errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK}:
        holders = lock_holders(port, roots)
        return PortUnavailableError(
            _in_use_text(port, holders, roots, shared_bus, busy=code == errno.EBUSY),
            port=port,
            reason=PortReason.IN_USE,
            holder=holders[0] if holders else None,
        )
    return PortUnavailableError(
        f"cannot open {port}: {strerror(exc)} (the driver's own error)",
        port=port,
        reason=PortReason.DRIVER,
    )


def _permission_text(port: str, roots: SystemRoots) -> str:
    user = _user_name(os.geteuid())
    try:
        info = roots.node(port).stat()
    except OSError:
        return f"cannot open {port}: permission denied for user {user}"
    group = _group_name(info.st_gid)
    return (
        f"cannot open {port}: permission denied (owner {_user_name(info.st_uid)}, group "
        f"{group}, mode {stat.S_IMODE(info.st_mode):04o}) for user {user}: add the user to {group} "
        f"(`sudo usermod -aG {group} {user}`, then log in again); the systemd unit needs "
        f"`SupplementaryGroups={group}`, a container `--group-add {group}`"
    )


def _user_name(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return str(uid)


def _group_name(gid: int) -> str:
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return str(gid)


def _in_use_text(
    port: str,
    holders: Sequence[int],
    roots: SystemRoots,
    shared_bus: Sequence[str],
    *,
    busy: bool = False,
) -> str:
    if busy and not holders:
        # EBUSY from open(): TIOCEXCL, set by a program that holds no lock on it, or left
        # by a process that died while another one still has the port open.
        return (
            f"cannot open {port}: the kernel refuses a second open (TIOCEXCL) and no "
            "process holds its lock: another program has it open (`fuser -v "
            f"{port}` names it), or one that had it ended while another still has it "
            "open. Close that program; two masters on one line corrupt each other's frames"
        )
    if holders:
        pid = holders[0]
        who = f"process {pid} ({describe_process(pid, roots)})"
        unit = systemd_unit_of(pid, roots)
        stop = (
            f"`systemctl stop {unit.removesuffix('.service')}`"
            if unit
            else f"`kill {pid}` or `systemctl stop {SERVICE_UNIT}` if it is the service"
        )
    else:
        who = "another program"
        stop = f"`systemctl stop {SERVICE_UNIT}` or the other `gateway` process"
    if shared_bus:
        listening = "; ".join(shared_bus)
        through = f"; or read through the running gateway's shared bus: {listening}"
    else:
        through = (
            "; or, if that gateway has `shared_bus.listen`, read through it on that address "
            "instead of the port"
        )
    return (
        f"cannot open {port}: it is in use by {who}, and two masters on one line "
        "corrupt each other's frames. "
        f"Stop it first ({stop}){through}"
    )


# --- who holds a port -------------------------------------------------------------------


def lock_holders(port: str, roots: SystemRoots) -> list[int]:
    """The PIDs that hold a lock on the port's node, from ``/proc/locks`` (proc(5))."""
    try:
        info = roots.node(port).stat()
        text = (roots.proc / "locks").read_text(encoding="ascii")
    except OSError:
        return []
    # "1: FLOCK  ADVISORY  WRITE 2735 00:1a:4 0 EOF": the PID, then the file system's
    # device (major:minor in hex) and the inode; "->" marks a waiter, not a holder.
    wanted = (os.major(info.st_dev), os.minor(info.st_dev), info.st_ino)
    pids = []
    for line in text.splitlines():
        fields = line.split()
        if len(fields) < 6 or fields[1] == "->":  # noqa: PLR2004 - the format above
            continue
        try:
            major, minor, inode = fields[5].split(":")
            where = (int(major, 16), int(minor, 16), int(inode))
            pid = int(fields[4])
        except ValueError:
            continue
        if where == wanted and pid > 0 and pid != os.getpid():
            pids.append(pid)
    return pids


def describe_process(pid: int, roots: SystemRoots) -> str:
    """A process's command line, shortened, for a message (``?`` if it cannot be read)."""
    try:
        raw = (roots.proc / str(pid) / "cmdline").read_bytes()
    except OSError:
        return "?"
    text = " ".join(part.decode(errors="replace") for part in raw.split(b"\0") if part)
    return text if len(text) <= 120 else text[:117] + "..."  # noqa: PLR2004 - one log line


def systemd_unit_of(pid: int, roots: SystemRoots) -> str | None:
    """The systemd service a process runs in, from its cgroup path (cgroups(7)), if any."""
    try:
        text = (roots.proc / str(pid) / "cgroup").read_text(encoding="utf-8")
    except OSError:
        return None
    for line in text.splitlines():
        for part in reversed(line.rpartition(":")[2].split("/")):
            if part.endswith(".service"):
                return part
    return None
