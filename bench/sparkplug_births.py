"""What a Sparkplug DBIRTH weighs, per sensor family: the default groups against all of them.

Each built-in profile is powered up in the simulator (its behaviour's nameplate and values),
every point it polls is decoded as the gateway decodes it (the unit registers resolved), and
the Sparkplug sink's reporter births the device once with the host's default groups
(process values and status) and once with every group. Printed: metrics and bytes of the
DBIRTH payload (protobuf, as it goes on the wire, ``seq`` aside). No broker is needed: the
payload's size does not depend on it.

Printed, and written to bench/results/sparkplug_births.json.
Run from the repository root: .venv/bin/python -m bench.sparkplug_births
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path

from gateway.line.samples import Quality, Sample
from gateway.profiles import PollGroup, Profile, builtin_profiles
from gateway.publish.sparkplug.catalogue import DEFAULT_GROUPS, Catalogue
from gateway.publish.sparkplug.reports import Reporter
from gateway.publish.sparkplug.topics import SparkplugTopics
from gateway.simulator import build_bus, parse_settings
from gateway.wire import codec

RESULTS = Path(__file__).parent / "results"
ALL_GROUPS = frozenset(g.value for g in PollGroup)


def samples_of(profile: Profile) -> list[Sample]:
    """Every polled point of a powered-up simulated sensor, decoded with its unit."""
    bus = build_bus(parse_settings({"devices": [{"profile": profile.id, "address": 1}]}))
    device = bus.devices[1]
    device.start(0.0)
    now = datetime.now(tz=UTC)
    values = {p.name: device.get(p.name) for p in profile.points if not p.view}
    out = []
    for point in profile.points:
        if point.view:
            continue
        value = values[point.name]
        unit = point.unit
        if point.unit_from is not None:
            selected = values.get(point.unit_from)
            if isinstance(selected, codec.EnumValue):
                unit = profile.point(point.unit_from).enum_units.get(selected.code)
        fault = value.name if isinstance(value, codec.Fault) else None
        value = None if isinstance(value, codec.Fault) else value
        out.append(
            Sample(
                bus="line1",
                device="sensor",
                profile=profile.id,
                point=point.name,
                value=value,
                fault=fault,
                unit=unit,
                quality=Quality.FAULT if fault else Quality.GOOD,
                monotonic=0.0,
                time=now,
                group=point.group.value,
            )
        )
    return out


def birth(profile: Profile, samples: list[Sample], groups: frozenset[str]) -> tuple[int, int]:
    """Metrics and payload bytes of the device's DBIRTH with ``groups``."""
    polled = [p.name for p in profile.points if not p.view]
    catalogue = Catalogue.build([("sensor", profile, polled)], groups=groups)
    reporter = Reporter(catalogue, SparkplugTopics("water", "gw"), birth_wait_s=0.0)
    (message,) = reporter.cycle(samples, live=True, now_ms=1_795_000_000_000)
    return len(catalogue.devices["sensor"].metrics), len(message.payload)


def main() -> None:
    """Print the table and keep the figures."""
    rows = []
    for profile in sorted(builtin_profiles().values(), key=lambda p: p.id):
        samples = samples_of(profile)
        default = birth(profile, samples, frozenset(str(g) for g in DEFAULT_GROUPS))
        every = birth(profile, samples, ALL_GROUPS)
        rows.append(
            {
                "profile": profile.id,
                "default_metrics": default[0],
                "default_bytes": default[1],
                "all_metrics": every[0],
                "all_bytes": every[1],
            }
        )
    print(f"{'profile':<26} {'default':>16} {'all groups':>18}")
    for row in rows:
        print(
            f"{row['profile']:<26} {row['default_metrics']:>4} metrics {row['default_bytes']:>5} B"
            f" {row['all_metrics']:>4} metrics {row['all_bytes']:>6} B"
        )
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "sparkplug_births.json").write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
