"""CPU control groups for the benches: a process's CPU to the nanosecond, and a CPU quota.

A control group counts the CPU of every thread and child of the processes in it, the
exited ones too, in nanoseconds (cgroup v1 ``cpuacct.usage``) or microseconds (v2
``cpu.stat`` ``usage_usec``): far finer than utime + stime in /proc, which tick every
10 ms, and without the threads that ended before a reading slipping through. With a
quota (v1 ``cpu.cfs_quota_us`` over ``cpu.cfs_period_us``, v2 ``cpu.max``) the kernel lets
the group run that much of each period and throttles it for the rest, as systemd's
``CPUQuota=`` does for a service (which writes the same files).

A process enters its group before it runs anything of its own: the bench starts it
through ``enter_argv``, a small interpreter that writes its own PID into the group's
``cgroup.procs`` and then execs the command, so the PID stays the command's.

Creating groups needs root (or a delegated subtree) and a cgroup file system with the cpu
controller (a quota) or cpuacct (v1) mounted; ``open_group`` says what is missing when it
cannot. Where no group can be made, ``SchedstatClock`` reads each thread's
``/proc/PID/task/TID/schedstat`` (nanoseconds on the CPU) over a process tree instead.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from collections.abc import Iterator, Sequence

PERIOD_US: Final = 100_000  # the kernel's default CFS period, and systemd's
MOUNTS: Final = Path("/proc/self/mounts")

# Run as ``python -c ENTER procs... -- argv...``: join the groups, then become the command.
ENTER: Final = """
import os, sys
split = sys.argv.index("--")
for procs in sys.argv[1:split]:
    with open(procs, "w") as out:
        out.write(str(os.getpid()))
os.execvp(sys.argv[split + 1], sys.argv[split + 1:])
"""


class CgroupError(RuntimeError):
    """No control group can be made here; the message names what is needed."""


@dataclass(frozen=True, slots=True)
class Throttling:
    """What the quota did: periods in which the group ran, those it was stopped in, for how long."""

    periods: int
    throttled: int
    throttled_s: float


@dataclass(frozen=True, slots=True)
class CpuGroup:
    """One control group made by the bench: where to enter it and what it reads.

    ``directories`` are the group's folders (two under cgroup v1 where cpu and cpuacct
    are mounted apart, one otherwise); ``version`` is 1 or 2.
    """

    version: int
    directories: tuple[Path, ...]
    cpu: Path | None  # the folder with the quota and its cpu.stat (None: accounting only)
    usage_file: Path  # v1 cpuacct.usage (ns), v2 cpu.stat (usage_usec)

    def enter_argv(self, argv: Sequence[str]) -> list[str]:
        """``argv`` started inside the group: the PID it gets is the command's own."""
        procs = [str(d / "cgroup.procs") for d in self.directories]
        return [sys.executable, "-c", ENTER, *procs, "--", *argv]

    def usage_s(self) -> float:
        """CPU seconds the group's processes have used (every thread, children, the exited)."""
        text = self.usage_file.read_text(encoding="utf-8")
        if self.version == 1:
            return int(text) / 1e9
        return _keyed(text)["usage_usec"] / 1e6

    def throttling(self) -> Throttling:
        """The quota's counters so far (zeros without a quota)."""
        if self.cpu is None:
            return Throttling(0, 0, 0.0)
        stat = _keyed((self.cpu / "cpu.stat").read_text(encoding="utf-8"))
        if self.version == 1:
            throttled_s = stat.get("throttled_time", 0) / 1e9
        else:
            throttled_s = stat.get("throttled_usec", 0) / 1e6
        return Throttling(stat.get("nr_periods", 0), stat.get("nr_throttled", 0), throttled_s)

    def pids(self) -> list[int]:
        """The processes in the group now."""
        text = (self.directories[0] / "cgroup.procs").read_text(encoding="utf-8")
        return [int(pid) for pid in text.split()]


def _keyed(text: str) -> dict[str, int]:
    """``key value`` lines (cpu.stat) as a dictionary."""
    pairs = (line.split() for line in text.splitlines())
    return {pair[0]: int(pair[1]) for pair in pairs if len(pair) == 2}  # noqa: PLR2004


def _mounts() -> list[tuple[str, Path, set[str]]]:
    """(type, mount point, options) of every cgroup file system mounted."""
    found = []
    for line in MOUNTS.read_text(encoding="utf-8").splitlines():
        fields = line.split()
        if len(fields) >= 4 and fields[2] in {"cgroup", "cgroup2"}:  # noqa: PLR2004
            found.append((fields[2], Path(fields[1]), set(fields[3].split(","))))
    return found


def _writable(directory: Path) -> bool:
    return os.access(directory, os.W_OK)


NEEDED: Final = (
    "a writable cgroup file system with the cpu controller: run as root on a host with "
    "cgroup v1 (cpu and cpuacct mounted under /sys/fs/cgroup) or cgroup v2 with 'cpu' in "
    "/sys/fs/cgroup/cgroup.controllers; in a container, one started with a writable "
    "cgroup (e.g. podman --cgroupns=private with cgroup v2). On a systemd host the same "
    "limit is `systemd-run --scope -p CPUQuota=25% gateway run --config FILE`."
)


@contextlib.contextmanager
def open_group(name: str, *, quota: float | None = None) -> Iterator[CpuGroup]:
    """A control group of our own for the block, removed after it (its processes gone).

    ``quota`` is a share of one core (0.25: 25 ms of every 100 ms); None makes a group
    that only counts. Raises ``CgroupError`` naming what is needed where none can be made.
    """
    group = _make(f"{name}-{os.getpid()}", quota)
    try:
        yield group
    finally:
        _remove(group)


def _make(name: str, quota: float | None) -> CpuGroup:
    mounts = _mounts()
    v1_cpu = next((p for kind, p, opts in mounts if kind == "cgroup" and "cpu" in opts), None)
    v1_acct = next((p for kind, p, opts in mounts if kind == "cgroup" and "cpuacct" in opts), None)
    if v1_cpu is not None and v1_acct is not None and _writable(v1_cpu) and _writable(v1_acct):
        return _make_v1(name, quota, v1_cpu, v1_acct)
    for kind, root, _ in mounts:
        if kind == "cgroup2" and _writable(root):
            controllers = (root / "cgroup.controllers").read_text(encoding="utf-8").split()
            if quota is None or "cpu" in controllers:
                return _make_v2(name, quota, root)
    raise CgroupError(f"no control group can be made here; needed: {NEEDED}")


def _make_v1(name: str, quota: float | None, cpu_root: Path, acct_root: Path) -> CpuGroup:
    roots = [cpu_root] if cpu_root == acct_root else [cpu_root, acct_root]
    directories = tuple(root / name for root in roots)
    for directory in directories:
        directory.mkdir(exist_ok=True)
    cpu = cpu_root / name
    if quota is not None:
        period = int((cpu / "cpu.cfs_period_us").read_text(encoding="utf-8"))
        (cpu / "cpu.cfs_quota_us").write_text(str(round(quota * period)), encoding="utf-8")
    return CpuGroup(
        version=1,
        directories=directories,
        cpu=cpu if quota is not None else None,
        usage_file=acct_root / name / "cpuacct.usage",
    )


def _make_v2(name: str, quota: float | None, root: Path) -> CpuGroup:
    if quota is not None:
        # A group's controllers are those its parent hands down; the root may hold
        # processes of its own ("no internal processes" spares it).
        (root / "cgroup.subtree_control").write_text("+cpu", encoding="utf-8")
    directory = root / name
    directory.mkdir(exist_ok=True)
    if quota is not None:
        (directory / "cpu.max").write_text(
            f"{round(quota * PERIOD_US)} {PERIOD_US}", encoding="utf-8"
        )
    return CpuGroup(
        version=2,
        directories=(directory,),
        cpu=directory if quota is not None else None,
        usage_file=directory / "cpu.stat",
    )


def _remove(group: CpuGroup) -> None:
    """Remove the group's folders; processes still in it go back to the root group first."""
    for directory in group.directories:
        root = directory.parent
        with contextlib.suppress(OSError):
            for pid in (directory / "cgroup.procs").read_text(encoding="utf-8").split():
                with contextlib.suppress(OSError):
                    (root / "cgroup.procs").write_text(pid, encoding="utf-8")
        for _ in range(50):  # a process that just exited leaves its group a moment later
            try:
                directory.rmdir()
                break
            except FileNotFoundError:
                break
            except OSError:
                time.sleep(0.02)


class SchedstatClock:
    """CPU of a process tree from each thread's ``schedstat`` (ns), where no group can be made.

    Threads and children that ended between two readings take their time with them (a
    waited-for child's shows in its parent's cutime only, in ticks), so this undercounts a
    master that starts short-lived threads; the cgroup's count does not.
    """

    def __init__(self, pid: int) -> None:
        self.pid = pid

    def usage_s(self) -> float:
        """CPU seconds of every live thread of the process and its descendants."""
        total = 0
        for member in process_tree(self.pid):
            with contextlib.suppress(OSError):
                for task in Path(f"/proc/{member}/task").iterdir():
                    with contextlib.suppress(OSError, ValueError):
                        total += int((task / "schedstat").read_text(encoding="utf-8").split()[0])
        return total / 1e9


def _stat_fields(pid: int) -> list[str]:
    # The fields after the command name, which may hold spaces: ppid is [1].
    return Path(f"/proc/{pid}/stat").read_text(encoding="utf-8").rsplit(")", 1)[1].split()


def process_tree(pid: int) -> list[int]:
    """The process and every live descendant."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError, IndexError):
                parents[int(entry.name)] = int(_stat_fields(int(entry.name))[1])
    tree, frontier = [pid], [pid]
    while frontier:
        frontier = [p for p, parent in parents.items() if parent in frontier]
        tree.extend(frontier)
    return tree
