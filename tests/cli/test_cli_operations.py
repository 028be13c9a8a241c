"""``gateway set-clock``, ``measure`` and ``calibration-log`` as users run them.

A real ``gateway simulate --pty`` process plays the sensors; what was written and the
timing are read from its stats file, as an independent observer of the wire.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

from gateway.control.flash import LEDGER_FILE, FlashLedger
from tests.rigs import run_gateway, simulate_process, stats_of

if TYPE_CHECKING:
    from collections.abc import Iterator

pytestmark = [pytest.mark.line]

LINE = ("--baudrate", "19200", "--parity", "E")
HISTORY = """\
      history_0_x_zero: 0.5
      history_0_x_span: 21.75
      history_0_stamp: 2026-03-01 14:30:00
      history_1_x_zero: 0.25
      history_1_x_span: 22.0
      history_1_stamp: 2026-02-01 09:00:00
      history_2_x_zero: 7.0
      history_2_x_span: 99.0
      x_zero: 0.5
      x_span: 21.75
      calibration_stamp: 2026-03-01 14:30:00
"""


@pytest.fixture
def simulated_line(tmp_path: Path) -> Iterator[tuple[Path, Path]]:
    with simulate_process(
        tmp_path,
        "line: {baudrate: 19200, parity: E, stopbits: 1}\n"
        "devices:\n"
        "  - {profile: jumo-digiline-odo-s10, address: 1}\n"
        "  - {profile: jumo-digiline-odo-h10, address: 2}\n"
        "  - profile: jumo-tecline-cl2\n"
        "    address: 20\n"
        "    animate: false\n"
        "    values:\n" + HISTORY,
    ) as line:
        yield line


def gateway(cwd: Path, *args: str, tz: str = "UTC") -> subprocess.CompletedProcess[str]:
    """The command in ``cwd``, whose ``state/`` then holds the flash-write ledger."""
    return run_gateway(*args, cwd=cwd, tz=tz)


def writes(data: dict[str, Any], address: int) -> list[tuple[int, int, list[int]]]:
    return [
        (w["function"], w["address"], w["values"]) for w in data["devices"][str(address)]["writes"]
    ]


def test_calibration_log_prints_the_history_as_json_and_as_a_table(
    simulated_line: tuple[Path, Path], tmp_path: Path
) -> None:
    port, stats = simulated_line
    device = ("--port", str(port), *LINE, "--address", "20", "--profile", "jumo-tecline-cl2")
    result = gateway(tmp_path, "calibration-log", *device, "--json")
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert data["current"] == {
        "x_zero": 0.5,
        "x_span": 21.75,
        "calibration_stamp": "2026-03-01T14:30:00",
    }
    assert data["entries"] == [
        {
            "index": 0,
            "empty": False,
            "x_zero": 0.5,
            "x_span": 21.75,
            "stamp": "2026-03-01T14:30:00",
        },
        {
            "index": 1,
            "empty": False,
            "x_zero": 0.25,
            "x_span": 22.0,
            "stamp": "2026-02-01T09:00:00",
        },
        {"index": 2, "empty": True},  # stamp 0: its 7.0 and 99.0 are leftovers, not shown
        {"index": 3, "empty": True},
        {"index": 4, "empty": True},
    ]
    table = gateway(tmp_path, "calibration-log", *device)
    assert table.returncode == 0, table.stderr
    assert "current calibration: x_zero 0.5 nA, x_span 21.75 nA/unit" in table.stdout
    assert "2026-02-01 09:00:00" in table.stdout
    assert table.stdout.count("(empty)") == 3
    assert "99.0" not in table.stdout
    data = stats_of(stats)
    assert data["timing_violations"] == 0
    assert writes(data, 20) == []


def test_set_clock_local_writes_the_hosts_zone_and_counts_the_flash_write(
    simulated_line: tuple[Path, Path], tmp_path: Path
) -> None:
    port, stats = simulated_line
    device = ("--port", str(port), *LINE, "--address", "1", "--profile", "jumo-digiline-odo-s10")
    # POSIX TZ "XST-2": a zone two hours east of UTC, with no tz database needed.
    result = gateway(tmp_path, "set-clock", *device, "--local", "--json", tz="XST-2")
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert data["written"].endswith("+02:00")
    assert data["registers"][6] == 120  # S10 6.9: offset to UTC in minutes
    assert abs(data["offset_after_s"]) < 1.5
    observed = stats_of(stats)
    assert writes(observed, 1) == [(16, 0x2840, data["registers"])]
    assert observed["timing_violations"] == 0
    # The S10 clock is flash-backed: counted in the ledger a running gateway shares.
    ledger = FlashLedger(tmp_path / "state" / LEDGER_FILE)
    assert ledger.totals() == {("address_1", "clock"): 1}
    ledger.close()
    table = gateway(tmp_path, "set-clock", *device)
    assert table.returncode == 0, table.stderr
    assert "before" in table.stdout
    assert "after" in table.stdout


def test_measure_prints_the_fresh_values(simulated_line: tuple[Path, Path], tmp_path: Path) -> None:
    port, stats = simulated_line
    device = ("--port", str(port), *LINE, "--address", "2", "--profile", "jumo-digiline-odo-h10")
    result = gateway(tmp_path, "measure", *device, "--json")
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert isinstance(data["oxygen"], float)
    assert data["oxygen_unit"] == "mg/l"
    assert data["temperature_unit"] == "°C"
    assert data["registers"] == [0, 5]
    observed = stats_of(stats)
    assert writes(observed, 2) == [(16, 0x3001, [0, 5])]
    assert observed["timing_violations"] == 0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["measure", "--address", "1", "--profile", "jumo-digiline-odo-s10"], "set_clock"),
        (["set-clock", "--address", "20", "--profile", "jumo-tecline-cl2"], "calibration_log"),
        (["measure", "--address", "2", "--profile", "jumo-digiline-odo-h10", "--wait", "0"], ""),
    ],
    ids=["measure-on-s10", "clock-on-tecline", "wait-zero"],
)
def test_refused_commands_exit_2_and_send_nothing(
    simulated_line: tuple[Path, Path], tmp_path: Path, args: list[str], message: str
) -> None:
    port, stats = simulated_line
    result = gateway(tmp_path, *args, "--port", str(port), *LINE)
    assert result.returncode == 2
    assert message in result.stderr
    assert stats_of(stats)["counters"].get("frames", 0) == 0


def test_a_silent_device_exits_1(simulated_line: tuple[Path, Path], tmp_path: Path) -> None:
    port, _ = simulated_line
    device = ("--port", str(port), *LINE, "--address", "7", "--profile", "reiss-m0c")
    result = gateway(tmp_path, "calibration-log", *device, "--timeout", "0.1")
    assert result.returncode == 1
    assert "could not read" in result.stderr
