"""The tests' tiers: what each test needs beyond Python, declared by markers and checked.

A test is marked by what it needs from the machine (:data:`MARKERS`, registered with pytest
here, and nowhere else): a line in real time, a broker, the browser, podman, root.

``scripts/test --quick`` runs the tests that need none of these. So that the quick tier
stays what it says, every test runs under a guard that notes what it used, from the setup
of its first fixture to the end of its body: a pty opened, a serial port or TCP line
opened, the simulator served on TCP, or a program started (``mosquitto``, ``gateway
simulate``, ``podman``, ``mount``, ...). A test that passed but used what its markers do
not declare fails, naming the marker it lacks and what it used. What a process the test
started does on its own (``gateway run`` opening its port) is that process's: the test
started the simulator or the broker it talks to, and that is what the guard sees.

Two more markers are not needs but an order: ``timing`` marks the tests that hold a line,
a sensor or the gateway's CPU to times, and those whose brokers take the machine's cores (a
three-node cluster), which ``scripts/test`` runs after the others, alone. ``side_by_side``
marks those of them that sleep through most of their time and follow the machine's pace as
they run (kill windows measured, rounds that go on until there is enough to check, a faulty
line's timeouts): they run three at a time, with nothing else beside them. A
``side_by_side`` test must be ``timing`` too.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    import pytest

MARKERS: Final[dict[str, str]] = {
    "line": "a line in real time: a pseudo-terminal or a TCP socket with the simulator, a"
    " converter or a misbehaving peer at its end, and the gateway's own timing on it",
    "broker": "a real MQTT broker (mosquitto, or the demo's embedded one)",
    "browser": "headless chromium, driven by playwright",
    "podman": "the container image built or run with podman, or the unit under a real systemd",
    "root": "mounts, loop devices, network namespaces, packet filters",
    "timing": "holds a line, a sensor or the gateway's CPU to times, or takes the machine's"
    " cores (a broker cluster): runs after the others, alone (an order, not a need)",
    "side_by_side": "a timing test that mostly sleeps and follows the machine's pace as it"
    " runs: three of these run side by side, nothing else beside them (an order, not a need)",
}
NEEDS: Final = ("line", "broker", "browser", "podman", "root")  # what the quick tier leaves out
# Where to note every test's needs as JSON lines (nodeid, used), for a survey of the suite.
RECORD_VARIABLE: Final = "GATEWAY_TEST_NEEDS_RECORD"

# Programs by what starting them needs (the base name of the program, or of the script).
_PROGRAMS: Final[dict[str, str]] = {
    "mosquitto": "broker",
    "amqtt": "broker",
    "nats-server": "broker",
    "rabbitmq-server": "broker",
    "rabbitmqctl": "broker",
    "epmd": "broker",
    "socat": "line",
    "mbpoll": "line",
    # A scraper and a metrics store in real time: only ever run with the gateway on a line.
    "prometheus": "line",
    "victoria-metrics": "line",
    "podman": "podman",
    "podman-compose": "podman",
    "runc": "podman",
    "test-image": "podman",
    "test-systemd": "podman",
    "systemd-nspawn": "podman",
    "mount": "root",
    "umount": "root",
    "losetup": "root",
    "mkfs.ext4": "root",
    "ip": "root",
    "iptables": "root",
}
# ``gateway COMMAND`` (or ``python -m gateway COMMAND``) by what the command brings up itself.
_GATEWAY_COMMANDS: Final[dict[str, tuple[str, ...]]] = {
    "simulate": ("line",),
    "demo": ("line", "broker"),  # simulated sensors on ptys, and an embedded broker
}


class Usage:
    """What the running test used, noted by the hooks below; one at a time."""

    def __init__(self) -> None:
        self.active = False
        self.used: dict[str, list[str]] = {}

    def note(self, need: str, what: str) -> None:
        if self.active:
            self.used.setdefault(need, []).append(what)

    def start(self) -> None:
        self.active, self.used = True, {}

    def stop(self) -> dict[str, list[str]]:
        self.active = False
        return self.used


USAGE: Final = Usage()


def needs_of_command(args: object) -> list[tuple[str, str]]:
    """What starting ``args`` (as :class:`subprocess.Popen` takes them) needs, and why."""
    if isinstance(args, (str, bytes, os.PathLike)):
        text = os.fsdecode(args)
        argv = shlex.split(text) if " " in text else [text]
    else:
        argv = [os.fsdecode(arg) for arg in args]  # type: ignore[attr-defined]
    if not argv:
        return []
    found = []
    program = Path(argv[0]).name
    if program in _PROGRAMS:
        found.append((_PROGRAMS[program], program))
    if "playwright" in " ".join(argv[:3]):
        found.append(("browser", "playwright's driver"))
    found.extend(
        (need, f"gateway {word}")
        for position, word in enumerate(argv)
        if word in _GATEWAY_COMMANDS and _runs_gateway(argv[:position])
        for need in _GATEWAY_COMMANDS[word]
    )
    return found


def _runs_gateway(before: Sequence[str]) -> bool:
    """Whether the arguments before a sub-command start the gateway's command line."""
    return bool(before) and (
        Path(before[-1]).name == "gateway"
        or (len(before) >= 2 and before[-2:] == ["-m", "gateway"])
    )


def _wrap(owner: Any, name: str, note: Callable[..., None]) -> None:
    """Replace ``owner.name`` by a function that calls ``note`` with its arguments first."""
    original = getattr(owner, name)

    def noted(*args: Any, **kwargs: Any) -> Any:
        note(*args, **kwargs)
        return original(*args, **kwargs)

    noted.__wrapped__ = original  # type: ignore[attr-defined]
    setattr(owner, name, noted)


def register(config: pytest.Config) -> None:
    """Declare the markers to pytest (``--strict-markers`` refuses any other)."""
    for name, meaning in MARKERS.items():
        config.addinivalue_line("markers", f"{name}: {meaning}")


def install() -> None:
    """Hook the places where a test reaches beyond Python; once per session."""
    import serial  # noqa: PLC0415 - the hooks are installed at the session's start

    from gateway.line.transports import modbus_tcp, rtu_over_tcp  # noqa: PLC0415
    from gateway.simulator.transport import SimulatorServer  # noqa: PLC0415

    def popen(_self: object, args: object, *_: object, **__: object) -> None:
        for need, what in needs_of_command(args):
            USAGE.note(need, what)

    _wrap(subprocess.Popen, "__init__", popen)
    _wrap(os, "openpty", lambda: USAGE.note("line", "a pseudo-terminal"))
    _wrap(serial.Serial, "open", lambda *_: USAGE.note("line", "a serial port"))
    _wrap(SimulatorServer, "open_tcp", lambda *_, **__: USAGE.note("line", "the simulator on TCP"))
    for module in (modbus_tcp, rtu_over_tcp):
        _wrap(module, "connect", lambda *_, **__: USAGE.note("line", "a TCP line"))


def declared(item: pytest.Item) -> set[str]:
    """The needs a test's markers declare."""
    return {need for need in NEEDS if item.get_closest_marker(need) is not None}


def undeclared(item: pytest.Item, used: dict[str, list[str]]) -> list[str]:
    """Each need used but not declared, with what used it."""
    missing = sorted(set(used) - declared(item))
    return [f"@pytest.mark.{need} ({', '.join(sorted(set(used[need])))})" for need in missing]


def failure(item: pytest.Item, used: dict[str, list[str]]) -> str | None:
    """Why ``item`` fails its markers: each need used but not declared, or an order that
    would put it beside others (``side_by_side`` without ``timing``); else None."""
    if item.get_closest_marker("side_by_side") and not item.get_closest_marker("timing"):
        return f"{item.nodeid} is marked side_by_side but not timing: add @pytest.mark.timing"
    missing = undeclared(item, used)
    if not missing:
        return None
    return f"{item.nodeid} used what its markers do not declare; add {'; '.join(missing)}"


def record(item: pytest.Item, used: dict[str, list[str]]) -> None:
    """Append what ``item`` used to the file ``$GATEWAY_TEST_NEEDS_RECORD`` names, if any."""
    path = os.environ.get(RECORD_VARIABLE)
    if path:
        line = json.dumps(
            {"test": item.nodeid, "used": sorted(used), "declared": sorted(declared(item))}
        )
        with Path(path).open("a", encoding="utf-8") as out:
            out.write(line + "\n")
