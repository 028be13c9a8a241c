"""``gateway demo --fleet N``: N cabinets' gateways on one machine, into one broker.

A plant runs one gateway per cabinet, each on its own small computer, all into one broker.
The fleet demo shows that on one machine: cabinet ``i`` (from 1) is a line of its own with
the single demo's simulated sensors (one of every family, the same faults and care
states, its own random seed), polled by a gateway of its own.

Each gateway is a process of its own, ``gateway run --config FILE``, exactly what a cabinet
runs: that is what "a fleet on one machine" should show, and N tasks in one process would
not. Each has its own interpreter and CPU figures (``top``, ``bench/fleet.py``), its own
config file and ``state_dir`` (spool, records, pid file: ``gateway reload`` and SIGHUP
reach one cabinet), its own MQTT session and its own failures. Its identity is the
cabinet's: MQTT client id ``gateway-demo-cabinet-01``, base topic ``demo/cabinet-01``,
``/metrics`` on ``--metrics-port`` + i - 1 (9108, 9109, ...), its web page on
``--web-port`` + i - 1 (every cabinet has its page, as every cabinet's computer has: the
operator at cabinet 3 calibrates there; one password for the run) and the shared bus on
``--modbus-port`` + i - 1; ``0`` turns the page or the shared bus off for the whole fleet.
The demo has no Sparkplug and no Home Assistant discovery: no edge node ids or unique ids
to tell apart.

What stays in this process is what is not a gateway: the simulated sensors (a cabinet's
line is hardware, not the gateway's CPU; they run here as in the single demo, one
pseudo-terminal per cabinet) and the broker, chosen as the single demo chooses it: the one
on localhost if it answers, else the embedded amqtt broker. For more than a few cabinets
run mosquitto on localhost: the embedded broker shares this process with the sensors.

The gateways log warnings and errors only (as the single demo shows them), each line
prefixed with its cabinet. Ctrl-C (SIGINT) or SIGTERM stops them all: each gets SIGTERM
and publishes its ``offline`` as it ends; one that has not ended after
:data:`SHUTDOWN_S` is killed. A gateway that ends by itself (a port taken) stops the
fleet, which ends with an error naming the cabinet and its exit status. Each is started
with the kernel's parent-death signal set, so none outlives this process, however it ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

import yaml
from rich.console import Console

from gateway.cli.demo import (
    DEMO_LINE,
    DEMO_SENSORS,
    Listen,
    WebPage,
    _broker,
    _config,
    _say,
    _shared_bus,
)
from gateway.config import parse_config
from gateway.errors import ConfigError, GatewayError

if TYPE_CHECKING:
    from collections.abc import Sequence

FLEET_MAX: Final = 50  # the dashboard's fleet view is made for 50 gateways (issue 39)
BASE_TOPIC: Final = "demo"  # cabinet i publishes under demo/cabinet-0i
SHUTDOWN_S: Final = 20.0  # how long the gateways have to end after SIGTERM
PR_SET_PDEATHSIG: Final = 1  # <linux/prctl.h>
# A cabinet's process: the parent-death signal set (it survives exec), then `gateway run`.
# A parent that ended before the prctl took effect is seen as a new parent id: stop then.
_CHILD: Final = (
    "import ctypes, os, signal, sys\n"
    f"ctypes.CDLL(None, use_errno=True).prctl({PR_SET_PDEATHSIG}, int(signal.SIGTERM))\n"
    "if os.getppid() != int(sys.argv[1]):\n"
    "    sys.exit(1)\n"
    "os.execv(sys.executable, [sys.executable, '-m', 'gateway', 'run', '--config', sys.argv[2],"
    " '--no-print'])\n"
)


@dataclass(frozen=True, slots=True)
class Cabinet:
    """One gateway of the fleet: its name, identity and ports.

    Example::

        Cabinet.number(3, metrics_port=9108, web_port=8080, modbus_port=0)
        # cabinet-03: demo/cabinet-03, /metrics on 9110, the page on 8082, no shared bus
    """

    name: str
    base_topic: str
    client_id: str
    metrics_port: int
    web_port: int  # 0: no page
    modbus_port: int  # 0: no shared bus

    @classmethod
    def number(cls, index: int, *, metrics_port: int, web_port: int, modbus_port: int) -> Cabinet:
        """Cabinet ``index`` (from 1): each port is the first cabinet's + index - 1."""
        name = f"cabinet-{index:02d}"
        step = index - 1
        return cls(
            name=name,
            base_topic=f"{BASE_TOPIC}/{name}",
            client_id=f"gateway-demo-{name}",
            metrics_port=metrics_port + step,
            web_port=web_port + step if web_port else 0,
            modbus_port=modbus_port + step if modbus_port else 0,
        )

    def ports(self) -> list[int]:
        """The ports this cabinet's gateway listens on."""
        return [p for p in (self.metrics_port, self.web_port, self.modbus_port) if p]


def plan(size: int, *, metrics_port: int, web_port: int, modbus_port: int) -> list[Cabinet]:
    """The fleet's cabinets; a ConfigError if two would listen on one port."""
    if not 1 <= size <= FLEET_MAX:
        raise ConfigError(f"--fleet {size}: from 1 to {FLEET_MAX} gateways")
    cabinets = [
        Cabinet.number(i, metrics_port=metrics_port, web_port=web_port, modbus_port=modbus_port)
        for i in range(1, size + 1)
    ]
    ports = [p for c in cabinets for p in c.ports()]
    if max(ports) > 65535:  # noqa: PLR2004 - the last TCP port
        raise ConfigError(f"--fleet {size}: the ports would go beyond 65535")
    if len(set(ports)) != len(ports):
        raise ConfigError(
            f"--fleet {size}: --metrics-port, --web-port and --modbus-port ranges overlap "
            f"(each cabinet takes the next port of each)"
        )
    return cabinets


def cabinet_config(
    cabinet: Cabinet,
    *,
    pty: Path,
    broker_port: int | None,
    listen: Listen,
    state_dir: Path,
    password: str,
) -> str:
    """The YAML of a cabinet's ``gateway run``: the single demo's, with the cabinet's identity."""
    text = _config(pty, broker_port, cabinet.metrics_port, listen, state_dir)
    if cabinet.web_port:
        text += WebPage(cabinet.web_port, password).config(listen)
    text += _shared_bus(cabinet.modbus_port, listen)
    document: dict[str, Any] = yaml.safe_load(text)
    if document["mqtt"].get("enabled", True):
        document["mqtt"] |= {"base_topic": cabinet.base_topic, "client_id": cabinet.client_id}
    # Warnings and errors, as the single demo shows them: N gateways' INFO is a flood.
    document["logging"] = {"level": "WARNING"}
    return yaml.safe_dump(document, sort_keys=False)


def _table(
    cabinets: Sequence[Cabinet], pids: Sequence[int], listen: Listen, *, mqtt: bool
) -> list[str]:
    """The fleet as aligned plain text: what runs where, ready to copy."""
    local = Listen.in_url(listen.client_host)
    header = ["cabinet", "pid", "metrics", "base topic"]
    pages = any(c.web_port for c in cabinets)
    shared = any(c.modbus_port for c in cabinets)
    if pages:
        header.append("web page")
    if shared:
        header.append("Modbus TCP")
    rows = [header]
    for cabinet, pid in zip(cabinets, pids, strict=True):
        row = [
            cabinet.name,
            str(pid),
            f"http://{local}:{cabinet.metrics_port}/metrics",
            cabinet.base_topic if mqtt else "- (no MQTT)",
        ]
        if pages:
            row.append(f"http://{local}:{cabinet.web_port}/")
        if shared:
            row.append(f"{local}:{cabinet.modbus_port}")
        rows.append(row)
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    return [
        "  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip() for row in rows
    ]


async def _relay(name: str, stream: asyncio.StreamReader, console: Console) -> None:
    """A gateway's output, each line prefixed with its cabinet."""
    while line := await stream.readline():
        _say(console, f"{name} | {line.decode(errors='replace').rstrip()}")


async def _start(config: Path) -> asyncio.subprocess.Process:
    """A cabinet's ``gateway run``, its output (stdout and stderr) on one pipe.

    Without the ``GATEWAY_*`` variables: the cabinet runs the file it was given, as the
    single demo runs its own config whatever the environment says.
    """
    environ = {k: v for k, v in os.environ.items() if not k.upper().startswith("GATEWAY_")}
    return await asyncio.create_subprocess_exec(
        sys.executable,
        "-c",
        _CHILD,
        str(os.getpid()),
        str(config),
        stdin=asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
        env=environ,
    )


async def _stop(processes: Sequence[asyncio.subprocess.Process]) -> None:
    """SIGTERM to every gateway still running; SIGKILL to one still there after SHUTDOWN_S."""
    for process in processes:
        if process.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                process.terminate()
    try:
        async with asyncio.timeout(SHUTDOWN_S):
            await asyncio.gather(*(p.wait() for p in processes))
    except TimeoutError:
        for process in processes:
            if process.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    process.kill()
        await asyncio.gather(*(p.wait() for p in processes))


async def run_fleet(
    size: int,
    *,
    mqtt_port: int = 1883,
    metrics_port: int = 9108,
    web_port: int = 8080,
    modbus_port: int = 1502,
    bind: str = "127.0.0.1",
) -> None:
    """Run ``size`` gateways, each with its own simulated cabinet, until SIGINT or SIGTERM."""
    from gateway.simulator import SimulatorServer, build_bus, parse_settings  # noqa: PLC0415

    listen = Listen.parse(bind)
    cabinets = plan(size, metrics_port=metrics_port, web_port=web_port, modbus_port=modbus_port)
    console = Console(soft_wrap=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    line = {
        "baudrate": DEMO_LINE.baudrate,
        "parity": DEMO_LINE.parity,
        "stopbits": DEMO_LINE.stopbits,
    }
    try:
        with tempfile.TemporaryDirectory(prefix="gateway-fleet-") as tmp:
            async with contextlib.AsyncExitStack() as stack:
                paths = []
                for index, cabinet in enumerate(cabinets, start=1):
                    directory = Path(tmp) / cabinet.name
                    directory.mkdir()
                    settings = {"line": line, "pace": True, "seed": index, "devices": DEMO_SENSORS}
                    simulator = SimulatorServer(build_bus(parse_settings(settings)))
                    simulator.open_pty(directory / "ttyDEMO")
                    stack.push_async_callback(simulator.close)
                    paths.append(directory)
                broker_port = await stack.enter_async_context(_broker(mqtt_port, listen, console))
                # GATEWAY_WEB__PASSWORD, or one made for the run: every cabinet's page takes it.
                password = WebPage.make(web_port).password
                configs = []
                for cabinet, directory in zip(cabinets, paths, strict=True):
                    text = cabinet_config(
                        cabinet,
                        pty=directory / "ttyDEMO",
                        broker_port=broker_port,
                        listen=listen,
                        state_dir=directory / "state",
                        password=password,
                    )
                    parse_config(text, environ={})  # a mistake is the demo's, said before any start
                    configs.append(directory / "gateway.yaml")
                    configs[-1].write_text(text, encoding="utf-8")
                await _run(
                    cabinets,
                    configs,
                    stop,
                    console=console,
                    listen=listen,
                    broker_port=broker_port,
                    password=password,
                )
    finally:
        for signum in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(signum)


async def _run(
    cabinets: Sequence[Cabinet],
    configs: Sequence[Path],
    stop: asyncio.Event,
    *,
    console: Console,
    listen: Listen,
    broker_port: int | None,
    password: str,
) -> None:
    """Start the gateways, say where they are, and stop them all on ``stop`` or a failure."""
    processes: list[asyncio.subprocess.Process] = []
    failed: list[tuple[Cabinet, int]] = []
    try:
        for config in configs:
            # One at a time, so that a failure on the way stops those already started.
            processes.append(await _start(config))  # noqa: PERF401
        _banner(
            console,
            cabinets,
            [p.pid for p in processes],
            listen=listen,
            broker_port=broker_port,
            password=password,
        )
        async with asyncio.TaskGroup() as tasks:
            for cabinet, process in zip(cabinets, processes, strict=True):
                assert process.stdout is not None  # noqa: S101 - piped above
                tasks.create_task(
                    _relay(cabinet.name, process.stdout, console),
                    name=f"demo.fleet[{cabinet.name}].output",
                )
            stopping = tasks.create_task(stop.wait(), name="demo.fleet.stop")
            ended = [
                tasks.create_task(p.wait(), name=f"demo.fleet[{c.name}].wait")
                for c, p in zip(cabinets, processes, strict=True)
            ]
            await asyncio.wait([stopping, *ended], return_when=asyncio.FIRST_COMPLETED)
            # One that ended by itself stops the fleet; a failure if it did not end cleanly
            # (exit status 0 is a gateway that was asked to stop: a Ctrl-C in the terminal
            # reaches every process of the group, and one may end before this one hears it).
            failed = [
                (c, p.returncode)
                for c, p in zip(cabinets, processes, strict=True)
                if p.returncode and not stop.is_set()
            ]
            stopping.cancel()
            await _stop(processes)
    finally:
        # A failure or a cancellation on the way: no gateway is left behind.
        await _stop(processes)
    if failed:
        cabinet, code = failed[0]
        raise GatewayError(
            f"{cabinet.name}'s gateway ended by itself (exit status {code}): "
            f"the fleet is stopped; its output is above"
        )


def _banner(
    console: Console,
    cabinets: Sequence[Cabinet],
    pids: Sequence[int],
    *,
    listen: Listen,
    broker_port: int | None,
    password: str,
) -> None:
    """The fleet's table and the commands to watch it."""
    local = listen.client_host
    _say(
        console,
        f"fleet: {len(cabinets)} gateways, each polling {len(DEMO_SENSORS)} simulated sensors "
        f"on its own line ({DEMO_LINE})",
    )
    for row in _table(cabinets, pids, listen, mqtt=broker_port is not None):
        _say(console, row)
    if broker_port is not None:
        _say(
            console,
            f"watch MQTT:  mosquitto_sub -h {local} -p {broker_port} "
            f"-t '{BASE_TOPIC}/+/+/state' -v",
        )
    if any(c.web_port for c in cabinets):
        _say(console, f"web pages:   sign in with the password {password} (every cabinet's)")
    if listen.bind.is_loopback:
        _say(console, f"listening on {listen.host} only: --bind 0.0.0.0 to serve other machines")
    else:
        _say(console, f"listening on {listen.host}: reachable from other machines")
    _say(console, "Ctrl-C stops the fleet.")
