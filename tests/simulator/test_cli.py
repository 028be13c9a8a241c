"""``gateway simulate`` as users run it: a process serving a pty, stopped with Ctrl-C."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gateway.simulator import build_bus, load_settings

MBPOLL = shutil.which("mbpoll")
ENV = {**os.environ, "COLUMNS": "200", "PYTHONIOENCODING": "utf-8"}


def start(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "gateway", "simulate", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
    )


def wait_ready(process: subprocess.Popen[str]) -> str:
    assert process.stdout is not None
    line = process.stdout.readline()
    assert line.startswith("simulating"), line + (process.stderr.read() if process.stderr else "")
    return line


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gateway", "simulate", *args],
        capture_output=True,
        text=True,
        check=False,
        timeout=30,
        env=ENV,
    )


@pytest.mark.line
def test_simulate_serves_until_ctrl_c_and_writes_stats(tmp_path: Path) -> None:
    port, stats = tmp_path / "ttySIM", tmp_path / "stats.json"
    config = tmp_path / "plant.yaml"
    config.write_text(
        "line: {baudrate: 19200, parity: E, stopbits: 1}\n"
        "devices:\n"
        "  - {profile: reiss-m0c, address: 10, animate: false, values: {temperature: 24.5}}\n",
        encoding="utf-8",
    )
    process = start(
        "--config",
        str(config),
        "-d",
        "jumo-digiline-odo-s10:1",
        "--pty",
        str(port),
        "--stats",
        str(stats),
    )
    try:
        line = wait_ready(process)
        assert "reiss-m0c@10" in line
        assert "jumo-digiline-odo-s10@1" in line
        assert "19200 8E1" in line
        assert MBPOLL is not None, (
            "mbpoll is missing: scripts/setup installs the Debian package (as root)"
        )
        result = subprocess.run(
            [
                MBPOLL,
                "-m",
                "rtu",
                "-a",
                "10",
                "-b",
                "19200",
                "-P",
                "even",
                "-0",
                "-1",
                "-r",
                "4",
                "-c",
                "1",
                "-t",
                "4:float",
                str(port),
            ],
            capture_output=True,
            text=True,
            check=False,
            timeout=20,
        )
        assert "[4]: \t24.5" in result.stdout, result.stdout
        time.sleep(0.4)  # one stats interval
        data = json.loads(stats.read_text(encoding="utf-8"))
        assert data["devices"]["10"]["requests"] == 1
    finally:
        process.send_signal(signal.SIGINT)
        _, errors = process.communicate(timeout=10)
    assert process.returncode == 0, errors
    assert not port.exists()
    assert json.loads(stats.read_text(encoding="utf-8"))["timing_violations"] == 0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["-d", "jumo-digiline-odo-s11:1", "--tcp", "127.0.0.1:0"],
            "unknown profile 'jumo-digiline-odo-s11'",
        ),
        (
            ["-d", "reiss-m0c:10", "-d", "reiss-m3c:10", "--tcp", "127.0.0.1:0"],
            "address 10 is already used",
        ),
        (
            ["-d", "reiss-m0c:10", "--pty", "/nonexistent/dir/ttySIM"],
            "cannot create /nonexistent/dir/ttySIM",
        ),
        (["-d", "reiss-m0c", "--tcp", "127.0.0.1:0"], "expected PROFILE:ADDRESS"),
        (["-d", "reiss-m0c:10"], "give --pty PATH and/or --tcp HOST:PORT"),
        (["--tcp", "127.0.0.1:0"], "give at least one --device"),
        (["-d", "reiss-m0c:300", "--tcp", "127.0.0.1:0"], "address"),
    ],
)
@pytest.mark.line
def test_bad_input_is_a_clear_error_and_non_zero_exit(args: list[str], message: str) -> None:
    result = run(*args)
    assert result.returncode == 2
    assert message in result.stderr


@pytest.mark.line
def test_existing_file_is_not_replaced(tmp_path: Path) -> None:
    target = tmp_path / "precious"
    target.write_text("keep", encoding="utf-8")
    result = run("-d", "reiss-m0c:10", "--pty", str(target))
    assert result.returncode == 2
    assert "exists and is not a link" in result.stderr
    assert target.read_text(encoding="utf-8") == "keep"


def test_the_shipped_example_loads() -> None:
    example = Path(__file__).parents[2] / "config" / "simulator-plant.yaml"
    bus = build_bus(load_settings(example))
    families = {device.profile.family for device in bus.devices.values()}
    assert families == {
        "jumo-digiline-odo-s10",
        "jumo-digiline-odo-h10-h20",
        "jumo-tecline",
        "reiss-m0c-m3c",
    }
    assert str(bus.line) == "9600 8E1"
