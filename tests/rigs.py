"""Shared test rigs: the simulator on a real pseudo-terminal and a bus worker on its other end.

Every test that talks to a simulated sensor uses these, so each test file does not grow
its own copy of the set-up.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from gateway.control.link import DeviceLink
from gateway.line.engine.devices import DeviceTarget
from gateway.line.engine.worker import BusWorker
from gateway.line.transports.serial_line import SerialLine
from gateway.profiles import PollGroup, get_profile
from gateway.shared.host_clock import TRUST_VARIABLE
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.wire.timing import LineFormat
from tests.unretrieved import reported_in
from tests.waiting import eventually

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Callable, Iterator, Sequence
    from pathlib import Path

    from gateway.line.boundary import Line
    from gateway.line.samples import DeviceEvent, Sample
    from gateway.simulator.device import SimulatedDevice, WriteRecord


@dataclass
class ListSink:
    samples: list[Sample] = field(default_factory=list)
    events: list[DeviceEvent] = field(default_factory=list)

    async def publish(self, samples: Sequence[Sample]) -> None:
        self.samples.extend(samples)

    async def device_event(self, event: DeviceEvent) -> None:
        self.events.append(event)

    def good(self, device: str, point: str) -> list[Sample]:
        return [s for s in self.samples if (s.device, s.point) == (device, point) and s.good]


def target(
    name: str,
    profile_id: str,
    address: int,
    *,
    interval: float = 0.5,
    groups: Sequence[PollGroup] = (PollGroup.PROCESS, PollGroup.STATUS),
    **options: Any,
) -> DeviceTarget:
    profile = get_profile(profile_id)
    intervals: dict[str, float | None] = {}
    for point in profile.points:
        if point.view:
            continue
        if point.group in groups:
            intervals[point.name] = interval
        elif point.group is PollGroup.IDENTITY:
            intervals[point.name] = None
    return DeviceTarget(name=name, address=address, profile=profile, intervals=intervals, **options)


@dataclass
class Rig:
    server: SimulatorServer
    worker: BusWorker
    sink: ListSink
    line: Line

    async def run_for(self, seconds: float) -> None:
        task = asyncio.create_task(self.worker.run())
        await asyncio.sleep(seconds)
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task

    async def run_until(self, done: Callable[[], bool], *, within_s: float) -> None:
        """Run the worker until ``done()`` holds, or fail after ``within_s``."""
        task = asyncio.create_task(self.worker.run())
        try:
            await eventually(lambda: done() or task.done(), within_s=within_s)
            if task.done():
                task.result()  # the worker's failure, as it is
                raise AssertionError("the worker stopped before the condition held")
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    def frames(self) -> list[Any]:
        return list(self.server.bus.frame_log)


@contextlib.asynccontextmanager
async def rig(
    tmp_path: Path,
    devices: list[dict[str, Any]],
    targets: list[DeviceTarget],
    *,
    line: dict[str, Any] | None = None,
    pace: bool = True,
    **worker_options: Any,
) -> AsyncIterator[Rig]:
    line = line or {"baudrate": 9600, "parity": "E", "stopbits": 1}
    server = SimulatorServer(
        build_bus(parse_settings({"devices": devices, "line": line, "pace": pace}))
    )
    port = tmp_path / "ttyRS485"
    server.open_pty(port)
    sink = ListSink()
    bus_line = SerialLine(port=str(port), line=LineFormat(**line))
    worker = BusWorker(name="line1", line=bus_line, devices=targets, sinks=[sink], **worker_options)
    try:
        yield Rig(server=server, worker=worker, sink=sink, line=bus_line)
    finally:
        await bus_line.close()
        await server.close()


PLANT = [
    {"profile": "jumo-digiline-odo-s10", "address": 1},
    {"profile": "jumo-digiline-odo-h10", "address": 2},
    {"profile": "jumo-digiline-odo-h20", "address": 3},
    {"profile": "jumo-tecline-cl2", "address": 20},
    {"profile": "reiss-m0c", "address": 10},
]


def plant_targets(interval: float = 0.5) -> list[DeviceTarget]:
    return [
        target("s10", "jumo-digiline-odo-s10", 1, interval=interval),
        target("h10", "jumo-digiline-odo-h10", 2, interval=interval),
        target("h20", "jumo-digiline-odo-h20", 3, interval=interval),
        target("cl2", "jumo-tecline-cl2", 20, interval=interval),
        target("m0c", "reiss-m0c", 10, interval=interval),
    ]


def link_target(name: str, profile_id: str, address: int) -> DeviceTarget:
    """A device polled for nothing: what the command line and link tests talk to."""
    return DeviceTarget(name=name, address=address, profile=get_profile(profile_id), intervals={})


@dataclass
class LinkRig:
    """One simulated line with links to its devices; the worker may poll meanwhile."""

    rig: Rig
    links: dict[str, DeviceLink]
    polling: asyncio.Task[None] | None = None

    @property
    def server(self) -> SimulatorServer:
        return self.rig.server

    def device(self, address: int) -> SimulatedDevice:
        """The simulated sensor at ``address`` (its registers, write log and behaviour)."""
        return self.rig.server.bus.devices[address]

    def writes(self, address: int) -> list[WriteRecord]:
        """The writes the sensor at ``address`` accepted or refused, oldest first."""
        return list(self.device(address).write_log)

    def violations(self) -> list[Any]:
        """Timing-rule violations the simulator's referee saw."""
        return list(self.rig.server.bus.violations)


@contextlib.asynccontextmanager
async def link_rig(
    tmp_path: Path,
    devices: list[dict[str, Any]],
    targets: list[DeviceTarget],
    *,
    poll: bool = False,
    line: dict[str, Any] | None = None,
    pace: bool = True,
) -> AsyncIterator[LinkRig]:
    """The simulator and links to ``targets``; with ``poll`` the worker runs its poll loop.

    Without ``poll`` the port is opened here and every read and write runs inline, as on
    the command line; with it, they queue on the running worker, as under MQTT commands.
    """
    async with rig(tmp_path, devices, targets, line=line, pace=pace) as base:
        links = {t.name: DeviceLink(base.worker, t.name) for t in targets}
        result = LinkRig(rig=base, links=links)
        if poll:
            result.polling = asyncio.create_task(base.worker.run())
            await asyncio.sleep(0)
        else:
            await base.line.open()
        try:
            yield result
        finally:
            if result.polling is not None:
                base.worker.request_stop()
                result.polling.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await result.polling


# --- the simulator as its own process, for the command-line tests -------------------------

STATS_INTERVAL_S = 0.35  # a little over the simulator's 250 ms between stats files


@contextlib.contextmanager
def simulate_process(directory: Path, config: str) -> Iterator[tuple[Path, Path]]:
    """``gateway simulate --pty`` on ``config`` (YAML text): yields the pty and the stats file.

    The simulator is an independent observer of the wire: what was written and the
    timing are read from its stats file.
    """
    port, stats = directory / "ttySIM", directory / "stats.json"
    path = directory / "sim.yaml"
    path.write_text(config, encoding="utf-8")
    command = [sys.executable, "-m", "gateway", "simulate", "--config", str(path)]
    with subprocess.Popen(
        [*command, "--pty", str(port), "--stats", str(stats)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    ) as simulator:
        stderr = ""
        try:
            assert simulator.stdout is not None
            assert simulator.stdout.readline().startswith("simulating")
            yield port, stats
        finally:
            # Stopped whatever happened in the test: Popen's own exit would wait for a
            # simulator that runs until it is told to stop.
            simulator.send_signal(signal.SIGINT)
            try:
                _, stderr = simulator.communicate(timeout=10)
            except subprocess.TimeoutExpired:
                simulator.kill()
                _, stderr = simulator.communicate(timeout=10)
    assert not reported_in(stderr), stderr


def stats_of(stats: Path) -> dict[str, Any]:
    """The simulator's stats file, once it has been written again."""
    time.sleep(STATS_INTERVAL_S)
    data: dict[str, Any] = json.loads(stats.read_text(encoding="utf-8"))
    return data


def run_gateway(
    *args: str, cwd: Path, stdin: str = "", tz: str | None = None, columns: int = 200
) -> subprocess.CompletedProcess[str]:
    """``gateway ARGS`` as a user runs it, in ``cwd`` (a command without --config keeps
    its ``state/`` there), with a wide terminal (``columns``) and, if given, a time zone.

    Whatever the command's outcome, an asyncio exception nobody retrieved fails the test.
    """
    env = {"COLUMNS": str(columns), "PATH": "/usr/bin:/bin", "PYTHONIOENCODING": "utf-8"}
    if TRUST_VARIABLE in os.environ:  # tests/conftest.py: the test host's clock is trusted
        env[TRUST_VARIABLE] = os.environ[TRUST_VARIABLE]
    if tz is not None:
        env["TZ"] = tz
    result = subprocess.run(
        [sys.executable, "-m", "gateway", *args],
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
        input=stdin,
        env=env,
        cwd=cwd,
    )
    assert not reported_in(result.stderr), result.stderr
    return result


def run_deploy_script(script: Path, *, timeout_s: float, cleanup_s: float) -> tuple[int, str]:
    """Run a script of ``deploy/`` in its own process group: its exit code and its output.

    Near ``timeout_s`` it gets SIGTERM, so that its trap removes its containers before
    pytest gives up on the test; ``cleanup_s`` is the allowance for that.
    """
    with subprocess.Popen(
        [str(script)],
        cwd=script.parent.parent,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # SIGTERM reaches the script and its podman commands alone
    ) as process:
        try:
            output, _ = process.communicate(timeout=timeout_s - cleanup_s)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGTERM)
            try:
                output, _ = process.communicate(timeout=cleanup_s / 2)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                output, _ = process.communicate()
            output += f"\n({script.name}: stopped after {timeout_s - cleanup_s:.0f} s)\n"
    return process.returncode, output


def assert_deploy_checks_pass(script: Path, *, timeout_s: float, cleanup_s: float) -> str:
    """Run a check script of ``deploy/``; assert every check passed; return its output.

    The output goes to stdout too, so that pytest shows every ok/FAIL line of a failure.
    """
    code, output = run_deploy_script(script, timeout_s=timeout_s, cleanup_s=cleanup_s)
    sys.stdout.write(output)
    failed = [line for line in output.splitlines() if line.startswith("FAIL: ")]
    assert code == 0, "\n".join(failed) or output[-3000:]
    assert f"deploy/{script.name}: every check passed" in output
    assert not failed
    return output
