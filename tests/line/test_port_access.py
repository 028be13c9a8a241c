"""Ports as real hardware needs them: exclusive, named by by-id, tuned, and why one is not open.

Real parts: the simulator's pseudo-terminals, real processes (``gateway run``, ``gateway
read``, a second gateway as an unprivileged user), the real ``/healthz``; only ``/dev``,
``/sys`` and ``/proc`` are fake trees where the machine has no USB adapter to show.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

from gateway.config import ConfigProblems, Rs485Config, parse_config
from gateway.errors import PortUnavailableError
from gateway.line.stats import LineStats
from gateway.line.transports.port_access import PortOptions, open_serial, release, rs485_settings
from gateway.line.transports.port_diagnosis import PortReason, lock_holders
from gateway.line.transports.port_names import SystemRoots, by_id_names_of, port_name_advice
from gateway.line.transports.serial_line import SerialLine
from gateway.line.transports.usb_adapter import read_latency_timer, usb_serial_of
from gateway.publish.prometheus import GatewayCollector, MetricsServer
from gateway.shared.state import GatewayState
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.wire.timing import LineFormat
from tests import paths
from tests.rigs import run_gateway, simulate_process

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Iterator

FORMAT = LineFormat(baudrate=9600, parity="E", stopbits=1)
FTDI_ID = "usb-FTDI_FT232R_USB_UART_A10K1234-if00-port0"
CH340_ID = "usb-1a86_USB_Serial-if00-port0"
NOBODY = 65534
PYTHON = (sys.executable, "-c")
SIMULATED = (
    "line: {baudrate: 9600, parity: E, stopbits: 1}\n"
    "devices:\n  - {profile: reiss-m0c, address: 10, animate: false,"
    " values: {concentration: 0.168}}\n"
)


@contextlib.asynccontextmanager
async def simulated_port(tmp_path: Path) -> AsyncIterator[Path]:
    """A simulated Reiss M0c at address 10 on a pseudo-terminal; yields its path."""
    line = {"baudrate": 9600, "parity": "E", "stopbits": 1}
    devices = [{"profile": "reiss-m0c", "address": 10}]
    server = SimulatorServer(build_bus(parse_settings({"devices": devices, "line": line})))
    port = tmp_path / "ttyRS485"
    server.open_pty(port)
    try:
        yield port
    finally:
        await server.close()


def fake_tree(tmp_path: Path) -> SystemRoots:
    """``/dev`` with two USB adapters (FTDI at ttyUSB0, CH340 at ttyUSB1) and their sysfs."""
    dev, sys_root = tmp_path / "dev", tmp_path / "sys"
    by_id = dev / "serial" / "by-id"
    by_id.mkdir(parents=True)
    drivers = sys_root / "bus/usb-serial/drivers"
    for node, link, driver in (("ttyUSB0", FTDI_ID, "ftdi_sio"), ("ttyUSB1", CH340_ID, "ch341")):
        (dev / node).touch()
        (by_id / link).symlink_to(f"../../{node}")
        (drivers / driver).mkdir(parents=True, exist_ok=True)
        device = sys_root / "bus/usb-serial/devices" / node
        device.mkdir(parents=True)
        (device / "driver").symlink_to(drivers / driver)
    (sys_root / "bus/usb-serial/devices/ttyUSB0/latency_timer").write_text("16\n")
    return SystemRoots(dev=dev, sys=sys_root, proc=Path("/proc"))


# --- the kernel's RS485 mode -------------------------------------------------------------


def test_the_rs485_block_reaches_pyserial_field_by_field() -> None:
    config = Rs485Config(
        rts_level_for_tx=False,
        rts_level_for_rx=True,
        delay_before_tx_ms=3,
        delay_before_rx_ms=40,
        rx_during_tx=True,
    )
    settings = rs485_settings(config)
    assert settings.rts_level_for_tx is False
    assert settings.rts_level_for_rx is True
    assert settings.delay_before_tx == pytest.approx(0.003)  # pyserial: seconds
    assert settings.delay_before_rx == pytest.approx(0.040)
    assert settings.loopback is True
    default = rs485_settings(Rs485Config())
    assert (default.rts_level_for_tx, default.rts_level_for_rx, default.loopback) == (
        True,
        False,
        False,
    )
    assert (default.delay_before_tx, default.delay_before_rx) == (0.0, 0.0)


def test_a_bus_takes_an_rs485_block() -> None:
    config = parse_config(
        "buses:\n"
        "  - name: line1\n"
        "    port: /dev/ttyAMA0\n"
        "    rs485: {rts_level_for_tx: true, delay_before_rx_ms: 2, rx_during_tx: false}\n"
    )
    assert config.buses[0].rs485 == Rs485Config(delay_before_rx_ms=2)


@pytest.mark.parametrize(
    ("block", "expected"),
    [
        (
            "{delay_before_tx: 2}",
            "buses[0].rs485.delay_before_tx (line 4): unknown key",
        ),
        (
            "{delay_before_rx_ms: 250}",
            "buses[0].rs485.delay_before_rx_ms (line 4): Input should be less than or equal to 100, got 250",
        ),
        (
            "{rts_level_for_tx: maybe}",
            "buses[0].rs485.rts_level_for_tx (line 4)",
        ),
    ],
)
def test_a_bad_rs485_block_is_refused_with_its_key_and_line(block: str, expected: str) -> None:
    with pytest.raises(ConfigProblems) as caught:
        parse_config(f"buses:\n  - name: line1\n    port: /dev/ttyAMA0\n    rs485: {block}\n")
    assert expected in str(caught.value)


def test_rs485_on_a_url_and_two_buses_on_one_port_are_refused() -> None:
    with pytest.raises(ConfigProblems) as caught:
        parse_config(
            "buses:\n"
            "  - {name: line1, port: /dev/ttyAMA0}\n"
            "  - {name: line2, port: /dev/ttyAMA0}\n"
            "  - {name: line3, port: 'socket://10.0.0.5:4001', rs485: {}}\n"
        )
    text = str(caught.value)
    assert (
        "buses[1].port (line 3): /dev/ttyAMA0 is already the port of buses[0] (line1): "
        "one bus per port, as it is opened exclusively"
    ) in text
    assert (
        "buses[2].rs485 (line 4): the kernel's RS485 mode applies to a serial device of this "
        "machine, not to socket://10.0.0.5:4001: the converter switches its own line; "
        "remove rs485"
    ) in text


@pytest.mark.line
async def test_a_pty_refuses_the_rs485_mode_as_documented(tmp_path: Path) -> None:
    async with simulated_port(tmp_path) as port:
        line = SerialLine(port=str(port), line=FORMAT, options=PortOptions(rs485=Rs485Config()))
        with pytest.raises(PortUnavailableError) as caught:
            await line.open()
        assert caught.value.reason == PortReason.NO_RS485
        assert str(caught.value) == (
            f"cannot open {port} in the kernel's RS485 mode: its driver has none "
            "(TIOCSRS485: Inappropriate ioctl for device). For a USB adapter: use one with "
            "automatic direction control and remove `rs485:` from the bus. For an RS485 HAT: "
            "load the driver its maker names in /boot/firmware/config.txt (e.g. "
            "`dtoverlay=sc16is752-spi1`: the sc16is7xx driver has the mode, and "
            "`linux,rs485-enabled-at-boot-time` in the overlay turns it on at boot), or use "
            "a HAT with automatic direction control and remove `rs485:`"
        )
        assert not line.is_open
        assert line.stats.port_problem == "no_rs485_mode"
        # The refusal closed the port and released its lock: it opens without the mode.
        plain = SerialLine(port=str(port), line=FORMAT)
        await plain.open()
        await plain.close()


# --- exclusive ports ---------------------------------------------------------------------


@pytest.mark.line
async def test_a_second_open_of_a_port_is_refused_and_a_close_releases_it(tmp_path: Path) -> None:
    async with simulated_port(tmp_path) as port:
        first = SerialLine(port=str(port), line=FORMAT)
        await first.open()
        second = SerialLine(port=str(port), line=FORMAT)
        with pytest.raises(PortUnavailableError) as caught:
            await second.open()
        assert caught.value.reason == PortReason.IN_USE
        assert str(caught.value).startswith(f"cannot open {port}: it is in use by ")
        assert second.stats.port_problem == "in_use"
        await first.close()
        await second.open()  # at once: close() waits for the device's close and its lock
        assert second.is_open
        assert second.stats.port_problem is None
        await second.close()


def _run_as_nobody(script: str) -> str:
    """A Python script as an unprivileged user (no CAP_SYS_ADMIN): its output."""
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("setpriv (util-linux) is needed to run as another user")
    result = subprocess.run(
        [setpriv, f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", *PYTHON, script],
        capture_output=True,
        text=True,
        check=False,
        timeout=30,
        cwd=paths.ROOT,
    )
    assert result.returncode == 0, result.stderr
    return result.stdout


OPEN_SCRIPT = """
import asyncio, json, sys
from gateway.errors import PortUnavailableError
from gateway.line.transports.serial_line import SerialLine
from gateway.wire.timing import LineFormat

async def main():
    try:
        await SerialLine(port=sys.argv[1], line=LineFormat()).open()
    except PortUnavailableError as exc:
        print(json.dumps({"reason": exc.reason, "holder": exc.holder, "message": str(exc)}))

sys.argv[1:] = [%r]
asyncio.run(main())
"""


RAW_OPEN_SCRIPT = """
import errno, os, sys
try:
    os.close(os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK))
    print("opened")
except OSError as exc:
    print(errno.errorcode[exc.errno])
"""


@pytest.mark.line
async def test_an_unprivileged_gateway_is_kept_out_by_the_lock(tmp_path: Path) -> None:
    # On a pseudo-terminal the lock alone guards the port (TIOCEXCL would outlive a killed
    # gateway there: the simulator keeps the slave open); it names the holder.
    async with simulated_port(tmp_path) as port:
        node = port.resolve()
        node.chmod(0o666)  # so that only the lock, not the mode, can refuse the open
        line = SerialLine(port=str(port), line=FORMAT)
        await line.open()
        try:
            raw = await asyncio.to_thread(
                _run_as_nobody, RAW_OPEN_SCRIPT.replace("sys.argv[1]", repr(str(node)))
            )
            out = await asyncio.to_thread(_run_as_nobody, OPEN_SCRIPT % str(node))
        finally:
            await line.close()
    assert raw.strip() == "opened"  # no TIOCEXCL on a pseudo-terminal
    refusal = json.loads(out)
    assert refusal["reason"] == "in_use"
    assert refusal["holder"] == os.getpid()  # found in /proc/locks
    assert refusal["message"].startswith(
        f"cannot open {node}: it is in use by process {os.getpid()} ("
    )


@pytest.mark.line
async def test_tiocexcl_refuses_other_opens_until_released(tmp_path: Path) -> None:
    async with simulated_port(tmp_path) as port:
        node = port.resolve()
        node.chmod(0o666)
        raw_open = RAW_OPEN_SCRIPT.replace("sys.argv[1]", repr(str(node)))
        device = open_serial(
            str(node), baudrate=9600, parity="N", stopbits=1, options=PortOptions(), tiocexcl=True
        )
        try:
            assert (await asyncio.to_thread(_run_as_nobody, raw_open)).strip() == "EBUSY"
            # Without the lock (a program that sets TIOCEXCL alone): the refusal says so.
            fcntl.flock(device.fileno(), fcntl.LOCK_UN)
            refusal = json.loads(await asyncio.to_thread(_run_as_nobody, OPEN_SCRIPT % str(node)))
            assert refusal["reason"] == "in_use"
            assert refusal["holder"] is None
            assert refusal["message"] == (
                f"cannot open {node}: the kernel refuses a second open (TIOCEXCL) and no "
                f"process holds its lock: another program has it open (`fuser -v {node}` "
                "names it), or one that had it ended while another still has it open. "
                "Close that program; two masters on one line corrupt each other's frames"
            )
            release(device)  # what Line.close() does first
            assert (await asyncio.to_thread(_run_as_nobody, raw_open)).strip() == "opened"
        finally:
            device.close()


@pytest.mark.line
async def test_permission_denied_names_the_group_to_join(tmp_path: Path) -> None:
    async with simulated_port(tmp_path) as port:
        node = port.resolve()
        node.chmod(0o660)
        group = node.stat().st_gid
        out = await asyncio.to_thread(_run_as_nobody, OPEN_SCRIPT % str(node))
    import grp  # noqa: PLC0415 - the test's own lookup of the name

    name = grp.getgrgid(group).gr_name
    refusal = json.loads(out)
    assert refusal["reason"] == "permission_denied"
    assert refusal["message"] == (
        f"cannot open {node}: permission denied (owner root, group {name}, mode 0660) for "
        f"user nobody: add the user to {name} (`sudo usermod -aG {name} nobody`, then log "
        f"in again); the systemd unit needs `SupplementaryGroups={name}`, a container "
        f"`--group-add {name}`"
    )


def test_lock_holders_are_read_from_proc_locks(tmp_path: Path) -> None:
    proc = tmp_path / "proc"
    proc.mkdir()
    node = tmp_path / "ttyUSB0"
    node.touch()
    info = node.stat()
    where = f"{os.major(info.st_dev):02x}:{os.minor(info.st_dev):02x}:{info.st_ino}"
    (proc / "locks").write_text(
        f"1: FLOCK  ADVISORY  WRITE 4242 {where} 0 EOF\n"
        f"1: -> FLOCK  ADVISORY  WRITE 4343 {where} 0 EOF\n"  # a waiter, not a holder
        "2: POSIX  ADVISORY  WRITE 99 00:1a:1 0 EOF\n"
    )
    roots = SystemRoots(dev=tmp_path, proc=proc)
    assert lock_holders(str(node), roots) == [4242]


# --- missing ports and by-id names ------------------------------------------------------


@pytest.mark.line
async def test_a_missing_port_lists_the_by_id_names_that_exist(tmp_path: Path) -> None:
    roots = fake_tree(tmp_path)
    line = SerialLine(port="/dev/ttyUSB7", line=FORMAT, options=PortOptions(roots=roots))
    with pytest.raises(PortUnavailableError) as caught:
        await line.open()
    assert caught.value.reason == PortReason.MISSING
    assert str(caught.value) == (
        "cannot open /dev/ttyUSB7: it does not exist; serial adapters connected now: "
        f"/dev/serial/by-id/{CH340_ID} (-> ttyUSB1), "
        f"/dev/serial/by-id/{FTDI_ID} (-> ttyUSB0)"
    )
    empty = SystemRoots(dev=tmp_path / "empty", proc=Path("/proc"))
    with pytest.raises(PortUnavailableError) as caught:
        await SerialLine(port="/dev/ttyUSB7", line=FORMAT, options=PortOptions(roots=empty)).open()
    assert str(caught.value) == (
        "cannot open /dev/ttyUSB7: it does not exist; no serial adapter is connected "
        "(nothing in /dev/serial/by-id): check the cable and the adapter, and `dmesg` for "
        "USB errors"
    )


def test_by_id_names_are_found_for_a_kernel_name(tmp_path: Path) -> None:
    roots = fake_tree(tmp_path)
    assert by_id_names_of("/dev/ttyUSB0", roots) == [f"/dev/serial/by-id/{FTDI_ID}"]
    assert port_name_advice("/dev/ttyUSB0", roots) == (
        "/dev/ttyUSB0 is numbered in the order adapters appear and can name another adapter "
        f"after a reboot or a replug; use its stable name: /dev/serial/by-id/{FTDI_ID}"
    )
    assert port_name_advice("/dev/ttyACM3", roots) == (
        "/dev/ttyACM3 is numbered in the order adapters appear and can name another adapter "
        "after a reboot or a replug; use its stable name under /dev/serial/by-id/ (none "
        "points at it now: is the adapter plugged in?)"
    )
    for stable in (f"/dev/serial/by-id/{FTDI_ID}", "/dev/ttyAMA0", "socket://10.0.0.5:4001"):
        assert port_name_advice(stable, roots) is None


def test_check_config_warns_on_kernel_names_and_keeps_its_exit_status(tmp_path: Path) -> None:
    roots = fake_tree(tmp_path)
    config = tmp_path / "gateway.yaml"
    config.write_text(
        "buses:\n"
        "  - name: line1\n"
        "    port: /dev/ttyUSB0\n"
        f"  - {{name: line2, port: /dev/serial/by-id/{CH340_ID}}}\n",
        encoding="utf-8",
    )
    result = run_gateway("check-config", str(config), "--dev-root", str(roots.dev), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == f"{config}: OK (1 warnings)"
    assert " ".join(result.stderr.split()) == (
        f"{config}: warning: buses[0].port (line 3): /dev/ttyUSB0 is numbered in the order "
        "adapters appear and can name another adapter after a reboot or a replug; use its "
        f"stable name: /dev/serial/by-id/{FTDI_ID}"
    )
    config.write_text(
        "buses:\n  - {name: line1, port: /dev/ttyUSB0, baudrate: 9601}\n", encoding="utf-8"
    )
    broken = run_gateway("check-config", str(config), "--dev-root", str(roots.dev), cwd=tmp_path)
    assert broken.returncode == 2
    assert "buses[0].baudrate (line 2)" in broken.stderr


# --- the USB latency timer -----------------------------------------------------------------


def test_the_ftdi_latency_timer_is_read_from_sysfs(tmp_path: Path) -> None:
    roots = fake_tree(tmp_path)
    ftdi = usb_serial_of(f"/dev/serial/by-id/{FTDI_ID}", roots)
    assert ftdi is not None
    assert (ftdi.node, ftdi.driver, ftdi.ftdi) == ("ttyUSB0", "ftdi_sio", True)
    assert read_latency_timer(ftdi, roots) == pytest.approx(0.016)
    ch340 = usb_serial_of("/dev/ttyUSB1", roots)
    assert ch340 is not None
    assert not ch340.ftdi
    assert usb_serial_of("/dev/ttyAMA0", roots) is None


@pytest.mark.line
async def test_an_ftdi_port_exports_its_latency_timer_and_warns_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    roots = fake_tree(tmp_path)
    async with simulated_port(tmp_path) as pty:
        # The pty stands in for the adapter's node: named ttyUSB0, as the fake sysfs knows it.
        port = tmp_path / "ttyUSB0"
        port.symlink_to(pty.resolve())
        line = SerialLine(port=str(port), line=FORMAT, options=PortOptions(roots=roots))
        with caplog.at_level(logging.DEBUG, logger="gateway.line.transports.usb_adapter"):
            for _ in range(2):
                await line.open()
                await line.close()
    assert line.stats.latency_timer_s == pytest.approx(0.016)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings == [
        (
            f"{port} (ttyUSB0, ftdi_sio) holds received bytes up to 16 ms (its USB latency "
            "timer): answers arrive late and the line carries fewer requests. Install the udev "
            "rule deploy/udev/99-gateway-ftdi-latency.rules (sets it to 1 ms at every "
            "plug-in), or once as root: `echo 1 > /sys/bus/usb-serial/devices/ttyUSB0/"
            "latency_timer`"
        )
    ]
    # A pty refuses TIOCSSERIAL's low-latency flag: noted for debugging, not fatal.
    assert any("low-latency mode refused" in r.getMessage() for r in caplog.records)
    state = GatewayState()
    state.add_line("line1", line.stats, list)
    metrics = {m.name: m for m in GatewayCollector(state).collect()}
    samples = metrics["gateway_port_latency_timer_seconds"].samples
    assert [(s.labels, round(s.value, 6)) for s in samples] == [({"bus": "line1"}, 0.016)]


# --- /healthz says why ------------------------------------------------------------------


def _healthz(port: int) -> tuple[int, dict[str, Any]]:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=5) as answer:
            return answer.status, json.loads(answer.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


@pytest.mark.line
async def test_healthz_and_the_metrics_say_why_a_port_is_not_open(tmp_path: Path) -> None:
    roots = fake_tree(tmp_path)
    stats = LineStats()
    line = SerialLine(
        port="/dev/ttyUSB7", line=FORMAT, stats=stats, options=PortOptions(roots=roots)
    )
    with pytest.raises(PortUnavailableError):
        await line.open()
    state = GatewayState()
    state.add_line("line1", stats, list)
    with MetricsServer(state, host="127.0.0.1", port=0) as server:
        status, body = await asyncio.to_thread(_healthz, server.port)
    assert status == 503
    bus = body["buses"]["line1"]
    assert bus["port_open"] is False
    assert bus["port_problem"] == "missing"
    assert bus["port_error"].startswith("cannot open /dev/ttyUSB7: it does not exist; ")
    assert body["reasons"] == [
        f"bus line1: port not open (0 failures): missing: {bus['port_error']}"
    ]
    metrics = {m.name: m for m in GatewayCollector(state).collect()}
    problem = metrics["gateway_bus_port_problem"].samples
    assert [(s.labels, s.value) for s in problem] == [({"bus": "line1", "reason": "missing"}, 1.0)]


# --- two processes on one port -------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@pytest.fixture
def running_gateway(tmp_path: Path) -> Iterator[tuple[Path, Path, subprocess.Popen[str]]]:
    """``gateway run`` polling a simulated line: yields the port, its config and the process."""
    with simulate_process(tmp_path, SIMULATED) as (port, _stats):
        config = tmp_path / "gateway.yaml"
        metrics, shared = _free_port(), _free_port()
        config.write_text(
            f"buses:\n  - {{name: line1, port: {port}, baudrate: 9600, parity: E}}\n"
            "devices:\n  - {name: basin, bus: line1, address: 10, profile: reiss-m0c}\n"
            "mqtt: {enabled: false}\n"
            f"prometheus: {{host: 127.0.0.1, port: {metrics}}}\n"
            f"state_dir: {tmp_path / 'state'}\n"
            f"shared_bus: {{listen: [{{host: 127.0.0.1, port: {shared}, framing: rtu}}]}}\n",
            encoding="utf-8",
        )
        with subprocess.Popen(
            [sys.executable, "-m", "gateway", "run", "--config", str(config), "--no-print"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        ) as process:
            deadline = time.monotonic() + 20
            while True:
                with contextlib.suppress(OSError, ValueError):
                    if _healthz(metrics)[1]["buses"]["line1"]["port_open"]:
                        break
                assert process.poll() is None, process.communicate()
                assert time.monotonic() < deadline, "gateway run never opened its port"
                time.sleep(0.1)
            yield port, config, process
            process.send_signal(signal.SIGTERM)
            process.communicate(timeout=15)


@pytest.mark.line
def test_gateway_read_beside_gateway_run_fails_fast_with_the_remedy(
    running_gateway: tuple[Path, Path, subprocess.Popen[str]], tmp_path: Path
) -> None:
    port, _config, process = running_gateway
    started = time.monotonic()
    result = run_gateway(
        "read", "--port", str(port), "--address", "10", "--profile", "reiss-m0c",
        "--baudrate", "9600", "--parity", "E", cwd=tmp_path,
    )  # fmt: skip
    assert time.monotonic() - started < 10
    assert result.returncode == 2
    message = " ".join(result.stderr.split())  # rich folds long lines
    assert f"error: cannot open {port}: it is in use by process {process.pid} (" in message
    assert "gateway run --config" in message
    assert (
        "and two masters on one line corrupt each other's frames. Stop it first (`kill "
        f"{process.pid}` or `systemctl stop rs485-gateway` if it is the service); or, if "
        "that gateway has `shared_bus.listen`, read through it on that address instead of "
        "the port"
    ) in message


@pytest.mark.line
def test_a_second_gateway_run_fails_fast_and_names_the_shared_bus(
    running_gateway: tuple[Path, Path, subprocess.Popen[str]], tmp_path: Path
) -> None:
    port, config, process = running_gateway
    second = tmp_path / "second.yaml"
    text = config.read_text(encoding="utf-8")
    shared = int(text.rsplit("port: ", 1)[1].split(",")[0])
    metrics = text.split("prometheus: {host: 127.0.0.1, port: ")[1].split("}")[0]
    # The same config but for the metrics port: the port in use stops it before its
    # shared bus would find its address taken too.
    second.write_text(text.replace(f"port: {metrics}}}", f"port: {_free_port()}}}"))
    started = time.monotonic()
    result = run_gateway("run", "--config", str(second), "--no-print", cwd=tmp_path)
    assert time.monotonic() - started < 15
    assert result.returncode == 2, result.stderr
    message = " ".join(result.stderr.split())
    assert f"error: cannot open {port}: it is in use by process {process.pid} (" in message
    assert (
        f"or read through the running gateway's shared bus: RTU over TCP at 127.0.0.1:{shared} "
        f"(`gateway read --port socket://127.0.0.1:{shared} ...`)"
    ) in message
    assert process.poll() is None  # the first one polls on
