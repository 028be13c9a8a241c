"""The bus scan against the simulator on a real pseudo-terminal: what it finds, what it sends.

Tests check behaviour (devices, identification, requests per address, the referee's
verdict); sweep times are printed, never asserted.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import sys
import time
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

from gateway.config import check_config, load_config
from gateway.errors import BusClosedError, ConfigError
from gateway.line.scan import (
    FoundDevice,
    ScanReport,
    parse_addresses,
    probe_timeout_s,
    scan,
    scan_formats,
    supported_formats,
)
from gateway.line.transports.serial_line import SerialLine
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.wire.timing import LineFormat
from tests.unretrieved import reported_in

# A sweep asks dozens of silent addresses back to back, each held to its timeout and its
# inter-frame gap, which the simulator referees as the bytes come: alone, or a starved
# referee reads two requests as one gap-less burst.
pytestmark = pytest.mark.timing

if TYPE_CHECKING:
    from collections.abc import AsyncIterator

# Every family at an address no factory setting uses.
PLANT = [
    {"profile": "jumo-digiline-odo-s10", "address": 7},
    {"profile": "jumo-digiline-odo-h10", "address": 13},
    {"profile": "jumo-digiline-odo-h20", "address": 99},
    {"profile": "jumo-tecline-cl2", "address": 201},
    {"profile": "reiss-m0c", "address": 45},
    {"profile": "reiss-m3c", "address": 160},
]
EXPECTED = {
    7: ("digiline", "jumo-digiline-odo-s10", False),
    13: ("digiline", "jumo-digiline-odo-h10", False),
    45: ("reiss", "reiss-m0c", False),
    99: ("digiline", "jumo-digiline-odo-h20", False),
    160: ("reiss", "reiss-m3c", False),
    201: ("tecline", "jumo-tecline-cl2", True),
}
FAST: dict[str, Any] = {"baudrate": 115200, "parity": "N", "stopbits": 1}
FAST_LINE = LineFormat(baudrate=115200, parity="N", stopbits=1)
# The probe timeout is 30 ms + margin at any baud rate (digiLine t1); the simulator answers
# within 6 ms, so the full sweeps here wait 20 ms to stay short.
SHORT_TIMEOUT_S = 0.02
MAX_REQUESTS_SILENT = 1  # one probe: every family answers an unmapped read with exception 02
MAX_REQUESTS_FOUND = 5  # probes, then at most three identification reads


@contextlib.asynccontextmanager
async def simulated(
    tmp_path: Path, devices: list[dict[str, Any]], *, line: dict[str, Any] | None = None
) -> AsyncIterator[tuple[SimulatorServer, Path]]:
    settings = {"line": line or FAST, "pace": True, "devices": devices}
    server = SimulatorServer(build_bus(parse_settings(settings)))
    port = tmp_path / "ttyRS485"
    server.open_pty(port)
    try:
        yield server, port
    finally:
        await server.close()


def by_address(report: ScanReport) -> dict[int, FoundDevice]:
    return {device.address: device for device in report.devices}


def requests_per_address(server: SimulatorServer) -> Counter[int]:
    return Counter(record.device for record in server.bus.frame_log)


# --- the whole line ----------------------------------------------------------------------


@pytest.mark.line
async def test_full_sweep_finds_and_identifies_every_family(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    async with simulated(tmp_path, PLANT) as (server, port):
        started = time.monotonic()
        report = await scan(
            str(port),
            formats=[FAST_LINE],
            addresses=parse_addresses("1-247"),
            timeout_s=SHORT_TIMEOUT_S,
        )
        elapsed = time.monotonic() - started
        stats = server.bus.stats()
        sent = requests_per_address(server)
    with capsys.disabled():
        sys.stdout.write(
            f"\nscan 1-247 at {FAST_LINE}, probe timeout {SHORT_TIMEOUT_S * 1000:g} ms: "
            f"{elapsed:.2f} s, {report.requests} requests\n"
        )

    found = by_address(report)
    assert {a: (d.family, d.profile, d.guess) for a, d in found.items()} == EXPECTED
    assert stats["timing_violations"] == 0, stats["violations"][:3]
    s10, h20 = found[7], found[99]
    assert s10.details["device_name"] == "ODO S10"
    assert s10.details["sensor_type"] == "digiline_odo_s10"
    assert s10.details["serial_number"] == "S100000007"
    assert h20.details["oxygen_sub_type"] == "h20_trace_range"
    assert found[45].details["sensor_type"] == "CP4.0N-M0"
    assert found[160].details["sensor_type"] == "CP4.0N-M3"
    cl2 = found[201]
    assert cl2.details == {
        "hardware_version": 1130,
        "firmware_version": 1503,
        "serial_number": "0104714601000000201",
        "part_number": "00705172",
    }
    assert "cannot be read from the registers" in cl2.notes[0]
    assert all(device.line == FAST_LINE for device in report.devices)

    # Cost: two probes for a silent address, a handful of reads for a found one.
    assert report.requests == sum(sent.values())
    assert all(sent[a] == MAX_REQUESTS_SILENT for a in range(1, 248) if a not in EXPECTED)
    assert all(sent[a] <= MAX_REQUESTS_FOUND for a in EXPECTED)
    assert report.garbled == ()


@pytest.mark.line
async def test_config_snippet_passes_the_config_check(tmp_path: Path) -> None:
    async with simulated(tmp_path, PLANT) as (server, port):
        report = await scan(
            str(port),
            formats=[FAST_LINE],
            addresses=(7, 13, 45, 99, 160, 201, 202),
            timeout_s=SHORT_TIMEOUT_S,
        )
        config = tmp_path / "scanned.yaml"
        config.write_text(report.config_yaml(), encoding="utf-8")
        frames_before = server.bus.counters["frames"]
        assert port.exists()
        assert check_config(config, environ={}) == []
        # The checker reads the file only: nothing reached the line.
        assert server.bus.counters["frames"] == frames_before
    assert not port.exists()
    assert check_config(config, environ={}) == []  # ... and it never opens the port

    text = config.read_text(encoding="utf-8")
    assert f"port: {port}" in text
    assert "baudrate: 115200" in text
    assert text.count("  - name: ") == 7  # one bus, six devices
    for address, (family, profile, _guess) in EXPECTED.items():
        assert f"name: {family}_{address}\n" in text
        assert f"profile: {profile}" in text
    assert "profile: jumo-tecline-cl2  # guess" in text


@pytest.mark.line
async def test_config_snippet_pins_each_serial_number_read(tmp_path: Path) -> None:
    async with simulated(tmp_path, PLANT) as (_server, port):
        report = await scan(
            str(port), formats=[FAST_LINE], addresses=(7, 45, 201), timeout_s=SHORT_TIMEOUT_S
        )
    text = report.config_yaml()
    # Quoted: the tecLine's digits would be an (octal) number to YAML unquoted.
    assert '    profile: jumo-digiline-odo-s10\n    serial_number: "S100000007"\n' in text
    assert '    serial_number: "0104714601000000045"\n' in text
    assert (
        "    profile: jumo-tecline-cl2  # guess: check the nameplate\n"
        '    serial_number: "0104714601000000201"\n'
    ) in text
    config = tmp_path / "scanned.yaml"
    config.write_text(text, encoding="utf-8")
    pinned = {
        device.name: device.serial_number for device in load_config(config, environ={}).devices
    }
    assert pinned == {
        "digiline_7": "S100000007",
        "reiss_45": "0104714601000000045",
        "tecline_201": "0104714601000000201",
    }


# --- identification details --------------------------------------------------------------


@pytest.mark.line
async def test_tecline_variant_is_guessed_from_the_factory_address(tmp_path: Path) -> None:
    devices = [
        {"profile": "jumo-tecline-tc", "address": 30},
        {"profile": "jumo-tecline-o3", "address": 50},
        {"profile": "jumo-tecline-paa", "address": 71},
        {"profile": "reiss-m3c", "address": 20, "values": {"sensor_type": "CP4.0N"}},
    ]
    async with simulated(tmp_path, devices) as (server, port):
        report = await scan(
            str(port),
            formats=[FAST_LINE],
            addresses=(20, 30, 50, 71),
            timeout_s=SHORT_TIMEOUT_S,
        )
        assert server.bus.stats()["timing_violations"] == 0
    found = by_address(report)
    assert (found[30].profile, found[30].guess) == ("jumo-tecline-tc", True)
    assert "factory default address 30" in found[30].notes[0]
    assert (found[50].profile, found[50].guess) == ("jumo-tecline-o3", True)
    # Off the factory addresses no register tells PAA from Cl2: Cl2, marked a guess.
    assert (found[71].profile, found[71].guess) == ("jumo-tecline-cl2", True)
    # A Reiss sensor type without the -M0/-M3 suffix: the factory address decides, a guess.
    assert (found[20].family, found[20].profile, found[20].guess) == ("reiss", "reiss-m3c", True)
    assert "names no variant" in found[20].notes[0]


@pytest.mark.line
async def test_digiline_codes_without_an_exact_profile(tmp_path: Path) -> None:
    devices = [
        {"profile": "jumo-digiline-odo-s10", "address": 3},
        {"profile": "jumo-digiline-odo-s10", "address": 4},
        {"profile": "jumo-digiline-odo-h10", "address": 5},
    ]
    async with simulated(tmp_path, devices) as (server, port):
        sensors = server.bus.devices
        sensors[3].registers[0x010A] = 1  # a digiLine pH/ORP/T sensor: no profile
        sensors[4].registers[0x010B] = 9  # an S10 with an undocumented sub-type
        sensors[5].registers[0x010B] = 9  # H10 or H20? the sub-type does not say
        report = await scan(
            str(port),
            formats=[FAST_LINE],
            addresses=(3, 4, 5),
            timeout_s=SHORT_TIMEOUT_S,
        )
    found = by_address(report)
    ph = found[3]
    assert (ph.family, ph.profile) == ("digiline", None)
    assert ph.details == {"sensor_type": "digiline_ph_orp_t"}
    assert "no profile" in ph.notes[0]
    assert (found[4].profile, found[4].guess) == ("jumo-digiline-odo-s10", False)
    assert "sub-type unexpected" in found[4].notes[0]
    assert (found[5].profile, found[5].guess) == ("jumo-digiline-odo-h10", True)
    # The sensor without a profile stays out of the config, named in a comment.
    text = report.config_yaml()
    assert "address: 3\n" not in text
    assert "# address 3: no profile fits" in text


@pytest.mark.line
async def test_a_tecline_answering_the_digiline_sensor_type_is_still_identified(
    tmp_path: Path,
) -> None:
    """A tecLine or Reiss cell may answer 0 at 0x010A..0x010B (not in its manual) instead
    of exception 02: that answer names no digiLine, so the tecLine device data decides.

    Each device says which registers identified it; a cell that answers 02 there, as its
    manual says, costs no more reads than before.
    """
    undocumented_zeros = {0x010A: 0, 0x010B: 0}
    devices = [
        {"profile": "jumo-tecline-cl2", "address": 21, "registers": undocumented_zeros},
        {"profile": "jumo-tecline-cl2", "address": 22},  # exception 02 at 0x010A
        {"profile": "reiss-m0c", "address": 23, "registers": undocumented_zeros},
    ]
    async with simulated(tmp_path, devices) as (server, port):
        report = await scan(
            str(port), formats=[FAST_LINE], addresses=(21, 22, 23), timeout_s=SHORT_TIMEOUT_S
        )
        sent = requests_per_address(server)
        assert server.bus.stats()["timing_violations"] == 0
    found = by_address(report)
    tecline = "0x0308..0x0309 (tecLine device data)"
    for address in (21, 22):
        cell = found[address]
        assert (cell.family, cell.profile, cell.guess) == ("tecline", "jumo-tecline-cl2", True)
        assert cell.identified_by == tecline
        assert cell.details["hardware_version"] == 1130
        assert cell.details["serial_number"] == f"01047146010000000{address}"
    assert "0x010A" in "; ".join(found[21].notes)  # what it answered there is said
    reiss = found[23]
    assert (reiss.family, reiss.profile, reiss.guess) == ("reiss", "reiss-m0c", False)
    assert reiss.identified_by == f"{tecline}, 0x0300..0x0307 (Reiss sensor type)"
    # Two probes, the Reiss sensor type, serial and part number; no more.
    assert sent == {21: 5, 22: 5, 23: 5}
    assert all(n <= MAX_REQUESTS_FOUND for n in sent.values())
    # The table, the JSON and the config snippet say it.
    assert found[21].details_text().startswith(f"identified by {tecline}")
    assert report.as_dict()["devices"][0]["identified_by"] == tecline
    assert f"  # identified by {tecline}\n  - name: tecline_21\n" in report.config_yaml()


@pytest.mark.line
async def test_a_device_answering_only_exceptions_is_reported_unknown(tmp_path: Path) -> None:
    devices = [{"profile": "reiss-m0c", "address": 8, "unmapped": [0x0308]}]
    async with simulated(tmp_path, devices) as (server, port):
        report = await scan(
            str(port), formats=[FAST_LINE], addresses=(8,), timeout_s=SHORT_TIMEOUT_S
        )
        assert requests_per_address(server)[8] == 2  # both probes, each answered with 02
    (device,) = report.devices
    assert (device.family, device.profile, device.details) == ("unknown", None, {"exceptions": [2]})
    assert report.config_yaml() == ""  # nothing to configure


@pytest.mark.line
async def test_broken_answers_are_not_devices_but_are_reported(tmp_path: Path) -> None:
    devices = [{"profile": "jumo-digiline-odo-s10", "address": 9, "faults": {"crc": 1.0}}]
    async with simulated(tmp_path, devices) as (server, port):
        report = await scan(
            str(port), formats=[FAST_LINE], addresses=(8, 9), timeout_s=SHORT_TIMEOUT_S
        )
        assert requests_per_address(server)[9] == 4  # each probe once more after a bad CRC
    assert report.devices == ()
    assert report.garbled == ((FAST_LINE, 9),)


# --- formats ------------------------------------------------------------------------------


def test_supported_formats_come_from_the_profiles() -> None:
    formats = supported_formats()
    assert {f.baudrate for f in formats} == {2400, 4800, 9600, 19200, 38400, 57600, 115200}
    assert {(f.parity, f.stopbits) for f in formats} == {("N", 1), ("E", 1), ("O", 1), ("N", 2)}
    assert len(formats) == 28
    # digiLine's 9600/19200/38400 x 8N1/8O1/8E1/8N2 are all in.
    digiline = {
        LineFormat(baudrate=b, parity=p, stopbits=s)  # type: ignore[arg-type]
        for b in (9600, 19200, 38400)
        for p, s in (("N", 1), ("O", 1), ("E", 1), ("N", 2))
    }
    assert digiline <= set(formats)
    assert scan_formats(baudrate=19200, parity="E", stopbits=1) == (
        LineFormat(baudrate=19200, parity="E", stopbits=1),
    )
    every = scan_formats(baudrate=19200, parity="E", stopbits=1, every=True)
    assert every[0] == LineFormat(baudrate=19200, parity="E", stopbits=1)
    assert sorted(every, key=str) == sorted(formats, key=str)


@pytest.mark.line
async def test_all_formats_reopens_the_line_for_each(tmp_path: Path) -> None:
    opened: list[LineFormat] = []

    def recording_line(*, port: str, line: LineFormat) -> SerialLine:
        opened.append(line)
        return SerialLine(port=port, line=line)

    # A pty carries every format, but not every speed: an answer at 115200 baud comes
    # sooner than a 2400-baud line could carry it, and the gateway rightly refuses it (it
    # could only be an echo). The formats of eleven-bit characters at the simulated line's
    # rate take the same time (8N1's shorter gap would break the simulator's 8E1 rules).
    formats = tuple(
        fmt
        for fmt in scan_formats(baudrate=9600, parity="E", stopbits=1, every=True)
        if fmt.baudrate == 9600 and fmt.character_s == 11 / 9600
    )
    assert [str(f) for f in formats] == ["9600 8E1", "9600 8O1", "9600 8N2"]
    seen: list[tuple[str, int, int]] = []
    async with simulated(
        tmp_path,
        [{"profile": "jumo-digiline-odo-s10", "address": 7}],
        line={"baudrate": 9600, "parity": "E", "stopbits": 1},
    ) as (server, port):
        report = await scan(
            str(port),
            formats=formats,
            addresses=(7,),
            timeout_s=0.05,
            progress=lambda fmt, address, found: seen.append((str(fmt), address, found)),
            line_factory=recording_line,
        )
        assert server.bus.stats()["timing_violations"] == 0
    assert opened == list(formats)
    assert seen == [(str(fmt), 7, n) for n, fmt in enumerate(formats, start=1)]
    # A pty carries every format, so the sensor answers in each; the config takes the first.
    assert [d.line for d in report.devices] == list(formats)
    assert report.config_format == formats[0]
    text = report.config_yaml()
    assert "baudrate: 9600\n    parity: E\n" in text
    assert text.count("address: 7") == 1
    assert "# address" not in text


# --- input ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "addresses"),
    [
        ("1-247", tuple(range(1, 248))),
        ("7", (7,)),
        (" 1-3, 20 ,2", (1, 2, 3, 20)),
        ("247-247", (247,)),
    ],
)
def test_parse_addresses(text: str, addresses: tuple[int, ...]) -> None:
    assert parse_addresses(text) == addresses


@pytest.mark.parametrize("text", ["", "0-5", "1-248", "10-5", "a-b", "1..5", "1-5,", "-3"])
def test_parse_addresses_refuses(text: str) -> None:
    with pytest.raises(ConfigError, match="--addresses"):
        parse_addresses(text)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"baudrate": 9600, "parity": "X", "stopbits": 1}, "--parity must be N, E or O"),
        ({"baudrate": 9600, "parity": "N", "stopbits": 3}, "--stopbits 1 or 2"),
        ({"baudrate": 12345, "parity": "N", "stopbits": 1}, "--baudrate 12345"),
    ],
)
def test_scan_formats_refuses(options: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        scan_formats(**options)


def test_probe_timeout_is_the_answer_on_the_wire_plus_30_ms_and_a_margin() -> None:
    slow, fast = LineFormat(baudrate=2400), LineFormat(baudrate=115200)
    assert probe_timeout_s(slow) == pytest.approx(9 * 10 / 2400 + 0.040)
    assert probe_timeout_s(fast) == pytest.approx(9 * 10 / 115200 + 0.040)


@pytest.mark.line
async def test_a_port_that_cannot_be_opened_raises_before_sending(tmp_path: Path) -> None:
    with pytest.raises(BusClosedError, match="cannot open"):
        await scan(str(tmp_path / "ttyUSB9"), formats=[LineFormat()], addresses=(1,))


async def test_a_bad_timeout_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="--timeout"):
        await scan(str(tmp_path / "tty"), formats=[LineFormat()], addresses=(1,), timeout_s=0)


# --- the command --------------------------------------------------------------------------


async def gateway(*args: str) -> tuple[int, str, str]:
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "gateway",
        *args,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env={"COLUMNS": "200", "PATH": "/usr/bin:/bin", "PYTHONIOENCODING": "utf-8"},
        cwd=Path(__file__).parent,
    )
    stdout, stderr = await asyncio.wait_for(process.communicate(), timeout=90)
    assert process.returncode is not None
    assert not reported_in(stderr.decode()), stderr.decode()
    return process.returncode, stdout.decode(), stderr.decode()


@pytest.mark.line
async def test_scan_command_json(tmp_path: Path) -> None:
    line = {"baudrate": 19200, "parity": "E", "stopbits": 1}
    async with simulated(tmp_path, PLANT, line=line) as (server, port):
        code, stdout, stderr = await gateway(
            "scan",
            "--port",
            str(port),
            "--baudrate",
            "19200",
            "--parity",
            "E",
            "--addresses",
            "5-15,44-46,98-100,159-161,199-203",
            "--json",
        )
        stats = server.bus.stats()
        assert code == 0, stderr
        data = json.loads(stdout)
        config = tmp_path / "scanned.yaml"
        config.write_text(data["config"], encoding="utf-8")
        assert check_config(config, environ={}) == []
    assert stats["timing_violations"] == 0, stats["violations"][:3]
    assert "\x1b" not in stderr  # no progress bar with --json
    devices = {d["address"]: d for d in data["devices"]}
    assert {a: (d["family"], d["profile"], d["guess"]) for a, d in devices.items()} == EXPECTED
    assert devices[7]["format"] == "19200 8E1"
    assert devices[7]["identified_by"] == "0x010A..0x010B (digiLine sensor type)"
    assert devices[7]["name"] == "digiline_7"
    assert devices[160]["details"]["sensor_type"] == "CP4.0N-M3"
    assert "baudrate: 19200" in data["config"]
    assert data["formats"] == ["19200 8E1"]
    assert data["addresses"] == 25


@pytest.mark.line
async def test_scan_command_table_and_snippet(tmp_path: Path) -> None:
    async with simulated(tmp_path, PLANT) as (_server, port):
        code, stdout, stderr = await gateway(
            "scan", "--port", str(port), "--baudrate", "115200", "--addresses", "7,201"
        )
    assert code == 0, stderr
    table, _, snippet = stdout.partition("\n# gateway scan of")
    assert "jumo-digiline-odo-s10" in table
    assert "jumo-tecline-cl2 (guess)" in table
    assert "device_name=ODO S10" in table
    config = tmp_path / "scanned.yaml"
    config.write_text("# gateway scan of" + snippet, encoding="utf-8")
    assert check_config(config, environ={}) == []
    assert "2 device(s)" in stderr


@pytest.mark.line
async def test_scan_command_without_devices_exits_1(tmp_path: Path) -> None:
    async with simulated(tmp_path, PLANT) as (_server, port):
        code, stdout, stderr = await gateway(
            "scan", "--port", str(port), "--baudrate", "115200", "--addresses", "100-103", "--json"
        )
    assert code == 1
    assert json.loads(stdout)["devices"] == []
    assert json.loads(stdout)["config"] == ""
    assert "no device answered" in stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--addresses", "1-300"], "--addresses '1-300'"),
        (["--addresses", "seven"], "--addresses 'seven'"),
        (["--parity", "X"], "--parity must be N, E or O"),
        (["--timeout", "0"], "--timeout 0"),
    ],
)
@pytest.mark.line
async def test_scan_command_bad_input_exits_2(
    tmp_path: Path, args: list[str], message: str
) -> None:
    async with simulated(tmp_path, PLANT) as (server, port):
        code, _, stderr = await gateway("scan", "--port", str(port), *args)
        assert server.bus.counters["frames"] == 0  # nothing was sent
    assert code == 2
    assert message in stderr


async def test_scan_command_port_that_cannot_be_opened_exits_2(tmp_path: Path) -> None:
    code, _, stderr = await gateway("scan", "--port", str(tmp_path / "ttyUSB9"))
    assert code == 2
    assert "cannot open" in stderr
