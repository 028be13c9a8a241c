"""What one scrape of /metrics weighs: series, families and bytes, and what promtool says of them.

Two plants: the demo's (`gateway demo`: an S10, an H10, an H20 in fault, a tecLine Cl2, a
Reiss M0c and an M3c on one line at 19200 8E1, the S10 fed the tecLine's temperature) and
16 buses x 16 devices (S10, tecLine Cl2, Reiss M0c and H10 in turn, 115200 8N1, as
`publish.py` and `memory.py` have them). Each runs in a process of simulators apart, with
`gateway run --config` as its own process, MQTT to a local mosquitto. Once every point has
been read (every point is read once at the start; the scrape is taken when two scrapes a
few seconds apart have as many series), /metrics is scraped once and measured:

- **series**: sample lines of the exposition (what Prometheus stores per scrape);
- **families**: `# TYPE` lines;
- **bytes**: the exposition's size;
- **promtool**: the findings of `promtool check metrics` on it (0: none);
- **largest**: the three families with the most series.

For each variant of the `prometheus:` section: `default` (none of the keys: what the
gateway exports unless told otherwise), `all` (`groups:` every poll group), `legacy` (every
group and `legacy_names: true`). A gateway without these keys (before they existed) runs
only `default`, which was then every group under the old names: run this script from such
a checkout with `--variants default` for the figures before.

Printed, and written to bench/results/metrics_series.json. Run from the repository root:
.venv/bin/python -m bench.metrics_series [--plants demo,16x16] [--variants default,all,legacy]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

import yaml

from bench.publish import healthz, mosquitto, plant_config, simulators
from tests.mqtt_broker import free_port

if TYPE_CHECKING:
    from collections.abc import AsyncIterator

RESULTS = Path(__file__).parent / "results"
PROMTOOL = shutil.which("promtool") or "/usr/bin/promtool"
WARM_UP_S: Final = 5.0  # the start's reads of every point
SETTLE_S: Final = 3.0  # two scrapes this far apart with as many series: every point read
SETTLE_MAX_S: Final = 120.0
POLL_GROUPS: Final = ["process", "status", "diagnostics", "configuration", "identity"]
VARIANTS: Final[dict[str, dict[str, Any]]] = {
    "default": {},
    "all": {"groups": POLL_GROUPS},
    "legacy": {"groups": POLL_GROUPS, "legacy_names": True},
}

# The demo's sensors on their line, in a process apart (gateway.cli.demo's DEMO_SENSORS).
DEMO_SIMULATOR = """
import asyncio, sys
from pathlib import Path
from gateway.cli.demo import DEMO_LINE, DEMO_SENSORS
from gateway.simulator import SimulatorServer, build_bus, parse_settings
async def main(pty):
    line = {"baudrate": DEMO_LINE.baudrate, "parity": DEMO_LINE.parity,
            "stopbits": DEMO_LINE.stopbits}
    server = SimulatorServer(build_bus(parse_settings(
        {"line": line, "pace": True, "seed": 1, "devices": DEMO_SENSORS})))
    server.open_pty(Path(pty))
    print("ready", flush=True)
    await asyncio.Event().wait()
asyncio.run(main(sys.argv[1]))
"""


def demo_config(pty: Path, broker: int, directory: Path) -> dict[str, Any]:
    """The demo's gateway config (gateway.cli.demo) without its web page and shared bus."""
    from gateway.cli.demo import DEMO_LINE, DEMO_SENSORS, DEVICE_NAMES  # noqa: PLC0415

    return {
        "buses": [
            {
                "name": "demo",
                "port": str(pty),
                "baudrate": DEMO_LINE.baudrate,
                "parity": DEMO_LINE.parity,
                "stopbits": DEMO_LINE.stopbits,
            }
        ],
        "devices": [
            {
                "name": DEVICE_NAMES[sensor["address"]],
                "bus": "demo",
                "address": sensor["address"],
                "profile": sensor["profile"],
                "poll_interval": 1.0,
            }
            for sensor in DEMO_SENSORS
        ],
        "mqtt": {"host": "127.0.0.1", "port": broker, "base_topic": "demo"},
        "feeds": [
            {
                "device": "aeration_oxygen",
                "point": "compensation_temperature",
                "interval": 30,
                "deadband": 0.1,
                "source": {"device": "pool_chlorine", "point": "temperature"},
            }
        ],
        "state_dir": str(directory / "state"),
    }


@contextlib.asynccontextmanager
async def demo_plant(directory: Path, broker: int) -> AsyncIterator[dict[str, Any]]:
    """The demo's simulated line; the gateway's config for it."""
    pty = directory / "ttyDEMO"
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-c", DEMO_SIMULATOR, str(pty), stdout=asyncio.subprocess.PIPE
    )
    assert process.stdout is not None
    if await process.stdout.readline() != b"ready\n":
        await process.wait()
        raise RuntimeError("the demo's simulated line did not start")
    try:
        yield demo_config(pty, broker, directory)
    finally:
        process.terminate()
        await process.wait()


@contextlib.asynccontextmanager
async def grid_plant(
    directory: Path, broker: int, buses: int, devices: int
) -> AsyncIterator[dict[str, Any]]:
    """BUSES x DEVICES simulated lines (bench.publish's); the gateway's config for them."""
    async with simulators(directory, buses, devices) as (ports, _):
        config: dict[str, Any] = yaml.safe_load(plant_config(ports, devices, broker, directory))
        yield config


def scrape(port: int) -> str:
    """One scrape of /metrics."""
    url = f"http://127.0.0.1:{port}/metrics"
    with urllib.request.urlopen(url, timeout=60) as response:
        return str(response.read().decode())


def series(text: str) -> int:
    return sum(1 for line in text.splitlines() if line and not line.startswith("#"))


def measure(text: str) -> dict[str, Any]:
    """Series, families, bytes, promtool's findings and the largest families of a scrape."""
    lines = text.splitlines()
    by_family: Counter[str] = Counter()
    family = ""
    for line in lines:
        if line.startswith("# TYPE "):
            family = line.split()[2]
        elif line and not line.startswith("#"):
            by_family[family] += 1
    lint = subprocess.run(  # noqa: S603 - promtool on our own text
        [PROMTOOL, "check", "metrics"], input=text, capture_output=True, text=True, check=False
    )
    findings = [line for line in (lint.stdout + lint.stderr).splitlines() if line.strip()]
    return {
        "series": series(text),
        "families": sum(1 for line in lines if line.startswith("# TYPE ")),
        "bytes": len(text.encode()),
        "promtool_findings": len(findings),
        "largest": by_family.most_common(3),
    }


async def settled_scrape(port: int, process: asyncio.subprocess.Process, log: Path) -> str:
    """The scrape once two scrapes ``SETTLE_S`` apart have as many series."""
    deadline = time.monotonic() + SETTLE_MAX_S
    while True:
        try:
            await asyncio.to_thread(healthz, port)
        except OSError:
            if process.returncode is not None or time.monotonic() > deadline:
                text = await asyncio.to_thread(log.read_text, encoding="utf-8", errors="replace")
                tail = text[-3000:]
                raise RuntimeError(f"the gateway does not serve /metrics:\n{tail}") from None
            await asyncio.sleep(0.5)
        else:
            break
    await asyncio.sleep(WARM_UP_S)
    last = await asyncio.to_thread(scrape, port)
    while True:
        await asyncio.sleep(SETTLE_S)
        text = await asyncio.to_thread(scrape, port)
        if series(text) == series(last) or time.monotonic() > deadline:
            return text
        last = text


async def one(config: dict[str, Any], directory: Path, name: str, variant: str) -> dict[str, Any]:
    """`gateway run` with one variant of the prometheus section: its scrape measured."""
    port = free_port()
    config = config | {"prometheus": {"host": "127.0.0.1", "port": port, **VARIANTS[variant]}}
    path = directory / f"gateway-{variant}.yaml"
    path.write_text(yaml.safe_dump(config), encoding="utf-8")
    log = directory / f"gateway-{variant}.log"
    with log.open("wb") as output:
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "gateway",
            "run",
            "--config",
            str(path),
            "--no-print",
            stdout=asyncio.subprocess.DEVNULL,
            stderr=output,
        )
    try:
        text = await settled_scrape(port, process, log)
    finally:
        if process.returncode is None:
            process.terminate()
        await process.wait()
    (RESULTS / f"metrics-{name}-{variant}.txt").write_text(text, encoding="utf-8")
    return {"plant": name, "variant": variant, **measure(text)}


async def plant(
    name: str, broker: int, directory: Path, variants: list[str]
) -> list[dict[str, Any]]:
    """Every variant on one plant, the simulators started once."""
    run_dir = directory / name
    run_dir.mkdir()
    if name == "demo":
        context = demo_plant(run_dir, broker)
    else:
        buses, devices = (int(n) for n in name.split("x"))
        context = grid_plant(run_dir, broker, buses, devices)
    async with context as config:
        return [await one(config, run_dir, name, variant) for variant in variants]


async def main_async(args: argparse.Namespace) -> list[dict[str, Any]]:
    RESULTS.mkdir(exist_ok=True)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        with mosquitto(directory) as broker:
            for name in args.plants.split(","):
                results += await plant(name, broker, directory, args.variants.split(","))
    return results


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--plants", default="demo,16x16", help="demo and/or BUSESxDEVICES")
    parser.add_argument("--variants", default="default,all,legacy", help=", ".join(VARIANTS))
    args = parser.parse_args()
    os.environ.setdefault("COLUMNS", "200")
    results = asyncio.run(main_async(args))
    header = (
        f"{'plant':<7} {'variant':<8} {'series':>8} {'families':>8} {'bytes':>10} {'promtool':>8}"
    )
    print(header)
    for row in results:
        print(
            f"{row['plant']:<7} {row['variant']:<8} {row['series']:>8} {row['families']:>8} "
            f"{row['bytes']:>10} {row['promtool_findings']:>8}  largest: "
            + ", ".join(f"{name} {count}" for name, count in row["largest"])
        )
    (RESULTS / "metrics_series.json").write_text(json.dumps(results, indent=2), encoding="utf-8")


if __name__ == "__main__":
    main()
