"""Scale: 1, 4 and 16 buses with up to 30 simulated sensors each, MQTT and metrics on.

Each configuration runs the gateway in this process against simulated lines at 115200 8N1
(all simulators in one separate process) with every device polled at 1 s and a local
mosquitto, for --seconds after a warm-up. Printed per configuration, and written to
bench/results/scale.json:

- transactions and MQTT messages acknowledged per second, and how fast the queue of
  messages still to send grows (about 0 when MQTT keeps up with the polling);
- the gateway's CPU share of one core and its resident memory;
- the simulators' CPU share (both share this machine: a saturated simulator process makes
  every bus late, whatever the gateway does);
- whether every bus met its intervals: the worst poll lag and the deadlines missed.

Run from the repository root: .venv/bin/python -m bench.scale [--seconds 20]
[--matrix 1x30,4x30,16x30] [--profile FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import json
import tempfile
import time
from pathlib import Path

from bench.publish import mosquitto, plant_config, rss_mib, simulators
from bench.soak import process_figures
from gateway.app import run
from gateway.config import parse_config
from gateway.shared.state import GatewayState

RESULTS = Path(__file__).parent / "results"
POLL_INTERVAL_S = 1.0
WARM_UP_S = 6.0


async def one(
    broker: int,
    directory: Path,
    buses: int,
    devices: int,
    seconds: float,
    *,
    profile: Path | None = None,
) -> dict[str, object]:
    run_dir = directory / f"{buses}x{devices}"
    run_dir.mkdir()
    async with simulators(run_dir, buses, devices) as (ports, sim_pid):
        config = parse_config(plant_config(ports, devices, broker, run_dir), environ={})
        state = GatewayState()
        stop = asyncio.Event()
        gateway = asyncio.create_task(run(config, stop=stop, state=state))
        await asyncio.sleep(WARM_UP_S)

        def totals() -> tuple[int, int]:
            requests = sum(sum(line.requests.values()) for line in state.lines.values())
            missed = sum(h.missed_deadlines for h in state.health())
            return requests, missed

        requests0, missed0 = totals()
        published0, depth0 = state.mqtt.published, state.mqtt.queue_depth
        cpu0, wall0 = time.process_time(), time.monotonic()
        sim0 = process_figures(sim_pid)[1]
        worst_lag = 0.0
        end = wall0 + seconds
        profiler = cProfile.Profile()
        if profile:
            profiler.enable()
        while time.monotonic() < end:
            await asyncio.sleep(1.0)
            worst_lag = max([worst_lag, *(h.lag_s for h in state.health())])
        if profile:
            profiler.disable()
            profiler.dump_stats(profile.with_suffix(f".{buses}x{devices}.prof"))
        wall = time.monotonic() - wall0
        cpu = time.process_time() - cpu0
        sim = process_figures(sim_pid)[1] - sim0
        requests, missed = totals()
        depth = state.mqtt.queue_depth
        rss = rss_mib()
        stop.set()
        await asyncio.wait_for(gateway, timeout=60)
    return {
        "buses": buses,
        "devices_per_bus": devices,
        "devices": buses * devices,
        "transactions_per_s": (requests - requests0) / wall,
        "mqtt_messages_per_s": (state.mqtt.published - published0) / wall,
        # Messages waiting to be sent: flat when MQTT keeps up with the polling.
        "mqtt_queue_growth_per_s": (depth - depth0) / wall,
        "gateway_cpu_share": cpu / wall,
        # All of it (polling, decoding, MQTT, metrics) over the transactions on the lines.
        "cpu_us_per_transaction": 1e6 * cpu / max(requests - requests0, 1),
        "gateway_rss_mib": rss,
        "simulators_cpu_share": sim / wall,
        "worst_poll_lag_s": worst_lag,
        "missed_deadlines": missed - missed0,
        "meets_intervals": worst_lag < POLL_INTERVAL_S and missed == missed0,
    }


async def main_async(
    matrix: list[tuple[int, int]], seconds: float, profile: Path | None
) -> list[dict[str, object]]:
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        with mosquitto(directory) as broker:
            for buses, devices in matrix:
                results.append(
                    await one(broker, directory, buses, devices, seconds, profile=profile)
                )
                print(json.dumps(results[-1]), flush=True)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--matrix", default="1x8,1x30,4x30,16x30")
    parser.add_argument(
        "--profile",
        type=Path,
        help="write a cProfile of the measured window per configuration (FILE.<BxD>.prof)",
    )
    args = parser.parse_args()
    matrix = [(int(b), int(d)) for b, d in (item.split("x") for item in args.matrix.split(","))]
    results = asyncio.run(main_async(matrix, args.seconds, args.profile))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "scale.json").write_text(json.dumps(results, indent=2), encoding="utf-8")
    header = (
        f"{'buses':>5} {'devices':>7} {'tx/s':>7} {'msg/s':>7} {'queue/s':>7} {'CPU':>6} "
        f"{'µs CPU/tx':>9} "
        f"{'RSS MiB':>8} "
        f"{'sim CPU':>8} {'worst lag s':>11} {'missed':>6}  intervals met"
    )
    print(header)
    for r in results:
        print(
            f"{r['buses']:>5} {r['devices']:>7} {r['transactions_per_s']:>7.0f} "
            f"{r['mqtt_messages_per_s']:>7.0f} {r['mqtt_queue_growth_per_s']:>7.0f} "
            f"{r['gateway_cpu_share']:>6.0%} {r['cpu_us_per_transaction']:>9.0f} "
            f"{r['gateway_rss_mib']:>8.1f} {r['simulators_cpu_share']:>8.0%} "
            f"{r['worst_poll_lag_s']:>11.2f} {r['missed_deadlines']:>6}  "
            f"{'yes' if r['meets_intervals'] else 'no'}"
        )


if __name__ == "__main__":
    main()
