"""Prometheus: /metrics built from the gateway state, /healthz, and a real Prometheus scraping it.

The exposition is always read over HTTP from a started :class:`MetricsServer` and parsed
with prometheus-client's own parser; the last test runs the Debian ``prometheus`` server
(installed by ``scripts/setup``) against the gateway polling a simulated S10.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import re
import shutil
import socket
import subprocess
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from gateway.app import run
from gateway.config import parse_config
from gateway.errors import PublishError
from gateway.line.engine.health import DeviceHealth
from gateway.line.samples import Quality, Sample
from gateway.line.stats import LineStats
from gateway.publish.prometheus import MetricsServer, ValueNaming, value_naming
from gateway.shared.state import DeviceInfo, GatewayState, MqttStatus
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.wire.codec import BitfieldValue, EnumValue
from tests.mqtt_broker import free_port

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Callable, Iterator

    from gateway.wire.codec import Value

S10 = "jumo-digiline-odo-s10"
H10 = "jumo-digiline-odo-h10"
CL2 = "jumo-tecline-cl2"
PROMETHEUS = shutil.which("prometheus") or "/usr/bin/prometheus"


# --- HTTP and exposition helpers -----------------------------------------------------------


@dataclass(frozen=True)
class Reply:
    status: int
    content_type: str
    body: str

    def json(self) -> Any:
        return json.loads(self.body)


def fetch(url: str) -> Reply:
    """GET ``url`` (local only); error statuses are replies too."""
    try:
        with urllib.request.urlopen(url, timeout=5) as response:  # noqa: S310 - http://127.0.0.1
            return Reply(
                response.status, response.headers["Content-Type"], response.read().decode()
            )
    except urllib.error.HTTPError as exc:
        with exc:
            return Reply(exc.code, exc.headers["Content-Type"], exc.read().decode())


@dataclass(frozen=True)
class Exposition:
    text: str
    samples: list[tuple[str, dict[str, str], float]]
    families: dict[str, list[tuple[str, dict[str, str], float]]]

    @classmethod
    def parse(cls, text: str) -> Exposition:
        samples = []
        families: dict[str, list[tuple[str, dict[str, str], float]]] = {}
        for family in text_string_to_metric_families(text):
            rows = [(s.name, dict(s.labels), float(s.value)) for s in family.samples]
            families.setdefault(family.name, []).extend(rows)
            samples.extend(rows)
        return cls(text, samples, families)

    def find(self, name: str, **labels: str) -> list[tuple[dict[str, str], float]]:
        return [
            (have, value)
            for sample, have, value in self.samples
            if sample == name and labels.items() <= have.items()
        ]

    def value(self, name: str, **labels: str) -> float:
        found = self.find(name, **labels)
        assert len(found) == 1, f"{name}{labels}: {found}"
        return found[0][1]

    def labels(self, name: str, **labels: str) -> dict[str, str]:
        found = self.find(name, **labels)
        assert len(found) == 1, f"{name}{labels}: {found}"
        return found[0][0]


def scrape(server: MetricsServer) -> Exposition:
    reply = fetch(f"http://127.0.0.1:{server.port}/metrics")
    assert reply.status == 200
    assert reply.content_type.startswith("text/plain; version=0.0.4")
    return Exposition.parse(reply.body)


async def scrape_until(
    server: MetricsServer, until: Callable[[Exposition], bool], *, timeout_s: float = 10
) -> Exposition:
    """Scrape every 250 ms until ``until`` holds; the last scrape either way."""
    deadline = time.monotonic() + timeout_s
    while True:
        metrics = await asyncio.to_thread(scrape, server)
        if until(metrics) or time.monotonic() > deadline:
            return metrics
        await asyncio.sleep(0.25)


# --- a hand-filled gateway state -----------------------------------------------------------


def sample(
    device: str,
    profile: str,
    point: str,
    value: Value = None,
    *,
    bus: str = "line1",
    unit: str | None = None,
    fault: str | None = None,
    quality: Quality = Quality.GOOD,
    age_s: float = 0.0,
) -> Sample:
    return Sample(
        bus=bus,
        device=device,
        profile=profile,
        point=point,
        value=value,
        fault=fault,
        unit=unit,
        quality=quality,
        monotonic=time.monotonic() - age_s,
        time=datetime.now(tz=UTC),
        group="process",
    )


def line1_stats() -> LineStats:
    stats = LineStats()
    stats.requests.update({1: 120, 20: 80, 99: 3})
    stats.responses.update({1: 118, 20: 78})
    stats.errors.update({(1, "timeout"): 2, (20, "exception"): 1, (20, "crc"): 1})
    stats.errors[99, "stale_frame"] = 3  # answers of a device that is not configured
    stats.exception_codes[20, 2] = 1
    stats.retries[1] = 2
    stats.tolerated[1, "string_byte_count_16bit"] = 1
    for seconds in (0.012, 0.015, 0.018, 0.3):
        stats.observe_latency(1, seconds)
    stats.busy_s = 0.5
    stats.port_open = True
    stats.port_failures = 1
    return stats


def health_line1() -> list[DeviceHealth]:
    return [
        DeviceHealth(
            bus="line1",
            device="tank1_oxygen",
            address=1,
            online=True,
            failures_in_a_row=0,
            lag_s=0.004,
            missed_deadlines=3,
            unreadable_points=1,
        ),
        DeviceHealth(
            bus="line1",
            device="basin_chlorine",
            address=20,
            online=False,
            failures_in_a_row=5,
            lag_s=0.0,
            missed_deadlines=0,
            unreadable_points=0,
        ),
    ]


def health_line2() -> list[DeviceHealth]:
    return [
        DeviceHealth(
            bus="line2",
            device="tank2_oxygen",
            address=2,
            online=None,  # not heard of yet
            failures_in_a_row=0,
            lag_s=0.0,
            missed_deadlines=0,
            unreadable_points=0,
        )
    ]


def make_state() -> GatewayState:
    state = GatewayState()
    identity: dict[str, float | None] = {"serial_number": None, "software_version": None}
    for bus, name, profile, address in (
        ("line1", "tank1_oxygen", S10, 1),
        ("line1", "basin_chlorine", CL2, 20),
        ("line2", "tank2_oxygen", H10, 2),
    ):
        intervals: dict[str, float | None] = dict.fromkeys(
            ("temperature", "oxygen", "status", "cell_current", "concentration", "phase_shift"), 1.0
        )
        intervals["firmware_version"] = None
        state.add_device(
            DeviceInfo(
                bus=bus,
                name=name,
                profile=profile,
                address=address,
                intervals=intervals | identity,
            )
        )
    state.add_line("line1", line1_stats(), health_line1)
    line2 = LineStats()
    line2.port_open = True
    state.add_line("line2", line2, health_line2)
    status = BitfieldValue(
        raw=0b100,
        flags=(("oxygen_invalid", False), ("temperature_invalid", False), ("cap_missing", True)),
    )
    state.record(
        [
            sample("tank1_oxygen", S10, "temperature", 20.25, unit="°C"),
            sample("tank1_oxygen", S10, "oxygen", 98.5, unit="%sat", age_s=0.5),
            sample(
                "tank1_oxygen", S10, "oxygen", unit="%sat", fault="overrange", quality=Quality.FAULT
            ),
            sample(
                "tank1_oxygen", S10, "phase_shift", fault="timeout", quality=Quality.COMMS_ERROR
            ),
            sample("tank1_oxygen", S10, "status", status),
            sample(
                "tank1_oxygen", S10, "oxygen_unit", EnumValue(code=1, label="percent_saturation")
            ),
            sample("tank1_oxygen", S10, "analog_output_error_active", value=True),
            sample("tank1_oxygen", S10, "serial_number", "S10-0042"),
            sample("tank1_oxygen", S10, "software_version", "291.01.02"),
            sample("basin_chlorine", CL2, "concentration", 0.52, unit="ppm"),
            sample("basin_chlorine", CL2, "cell_current", 152.5, unit="nA"),
            sample("basin_chlorine", CL2, "temperature", 18.5, unit="°C", age_s=100.0),  # stale
            sample("basin_chlorine", CL2, "firmware_version", 263),
            sample("tank2_oxygen", H10, "oxygen", 8.5, bus="line2", unit="mg/l"),
        ]
    )
    state.mqtt = MqttStatus(enabled=True, connected=True, queue_max=1000, published=42)
    return state


@pytest.fixture
def state() -> GatewayState:
    return make_state()


@pytest.fixture
def server(state: GatewayState) -> Iterator[MetricsServer]:
    with MetricsServer(state, host="127.0.0.1", port=0) as metrics:
        yield metrics


# --- /metrics from a hand-filled state -----------------------------------------------------


def test_values_are_named_by_unit_with_bus_device_profile_labels(server: MetricsServer) -> None:
    metrics = scrape(server)
    device = {"bus": "line1", "device": "tank1_oxygen", "profile": S10}
    assert metrics.labels("gateway_temperature_celsius", device="tank1_oxygen") == device
    assert metrics.value("gateway_temperature_celsius", device="tank1_oxygen") == 20.25
    # A unit chosen by a unit register is a label; so is a fixed unit without a name.
    oxygen = metrics.labels("gateway_oxygen", device="tank2_oxygen")
    assert oxygen == {"bus": "line2", "device": "tank2_oxygen", "profile": H10, "unit": "mg/l"}
    assert metrics.value("gateway_oxygen", device="tank2_oxygen") == 8.5
    assert metrics.value("gateway_concentration", device="basin_chlorine", unit="ppm") == 0.52
    # In its base unit: the tecLine's 152.5 nA as amperes.
    assert metrics.value("gateway_cell_current_amperes", device="basin_chlorine") == 152.5e-9
    assert metrics.value("gateway_analog_output_error_active", device="tank1_oxygen") == 1.0


def test_a_fault_is_a_name_never_a_number(server: MetricsServer) -> None:
    metrics = scrape(server)
    assert metrics.find("gateway_oxygen", device="tank1_oxygen") == []
    assert (
        metrics.value(
            "gateway_value_fault", device="tank1_oxygen", point="oxygen", fault="overrange"
        )
        == 1.0
    )
    assert metrics.labels("gateway_value_fault") == {
        "bus": "line1",
        "device": "tank1_oxygen",
        "profile": S10,
        "point": "oxygen",
        "fault": "overrange",
    }
    # ... and the last good value's age keeps counting.
    assert metrics.value("gateway_value_age_seconds", device="tank1_oxygen", point="oxygen") >= 0.5
    assert all(abs(value) < 1e37 for _, _, value in metrics.samples)
    assert not re.search(r"\de\+?3[7-9]\b", metrics.text)


def test_comms_errors_and_stale_values_are_left_out(server: MetricsServer) -> None:
    metrics = scrape(server)
    assert metrics.find("gateway_phase_shift_degrees") == []
    assert metrics.find("gateway_value_fault", point="phase_shift") == []
    assert metrics.find("gateway_temperature_celsius", device="basin_chlorine") == []
    age = metrics.value("gateway_value_age_seconds", device="basin_chlorine", point="temperature")
    assert age >= 100.0
    # Identity is read once per connection: it has no age.
    assert metrics.find("gateway_value_age_seconds", point="serial_number") == []


def test_status_bits_enums_and_identity(server: MetricsServer) -> None:
    metrics = scrape(server)
    flags = {
        labels["flag"]: value
        for labels, value in metrics.find(
            "gateway_status_flag", device="tank1_oxygen", point="status"
        )
    }
    assert flags == {"oxygen_invalid": 0.0, "temperature_invalid": 0.0, "cap_missing": 1.0}
    assert metrics.labels("gateway_enum_info", point="oxygen_unit") == {
        "bus": "line1",
        "device": "tank1_oxygen",
        "profile": S10,
        "point": "oxygen_unit",
        "label": "percent_saturation",
        "code": "1",
    }
    info = {labels["device"]: labels for labels, _ in metrics.find("gateway_device_info")}
    assert info["tank1_oxygen"] == {
        "bus": "line1",
        "device": "tank1_oxygen",
        "profile": S10,
        "address": "1",
        "serial": "S10-0042",
        "firmware": "291.01.02",
        "hardware": "",  # not read: no hardware_version_major and _minor in this state
    }
    assert info["basin_chlorine"]["firmware"] == "263"
    assert info["tank2_oxygen"]["serial"] == ""  # not read yet


def test_bus_and_device_health(server: MetricsServer) -> None:
    metrics = scrape(server)
    tank1 = {"bus": "line1", "device": "tank1_oxygen"}
    assert metrics.value("gateway_requests_total", **tank1) == 120
    assert metrics.value("gateway_responses_total", **tank1) == 118
    assert metrics.value("gateway_retries_total", **tank1) == 2
    errors = {
        labels["kind"]: value for labels, value in metrics.find("gateway_errors_total", **tank1)
    }
    assert errors == {
        "timeout": 2,
        "crc": 0,
        "exception": 0,
        "wrong_address": 0,
        "stale_frame": 0,
        "noise": 0,
        "malformed": 0,
        "echo": 0,
        "echo_mismatch": 0,
        "no_silence": 0,
    }
    assert metrics.value("gateway_errors_total", device="basin_chlorine", kind="crc") == 1
    assert metrics.value("gateway_exceptions_total", device="basin_chlorine", code="02") == 1
    assert metrics.value("gateway_tolerated_quirks_total", quirk="string_byte_count_16bit") == 1
    # An address nobody configured keeps its number, and only what it has.
    assert metrics.value("gateway_requests_total", device="address_99") == 3
    assert metrics.value("gateway_errors_total", device="address_99", kind="stale_frame") == 3
    assert metrics.find("gateway_errors_total", device="address_99", kind="crc") == []
    buckets = {
        labels["le"]: value
        for labels, value in metrics.find("gateway_request_latency_seconds_bucket", **tank1)
    }
    assert (buckets["0.01"], buckets["0.02"], buckets["0.5"], buckets["+Inf"]) == (0, 3, 4, 4)
    assert metrics.value("gateway_request_latency_seconds_count", **tank1) == 4
    assert metrics.value("gateway_request_latency_seconds_sum", **tank1) == pytest.approx(0.345)
    assert 0 < metrics.value("gateway_bus_utilisation_ratio", bus="line1") <= 1
    assert metrics.value("gateway_bus_busy_seconds_total", bus="line1") == 0.5
    assert metrics.value("gateway_bus_port_open", bus="line1") == 1
    assert metrics.value("gateway_bus_port_failures_total", bus="line1") == 1
    assert metrics.value("gateway_device_online", device="tank1_oxygen") == 1
    assert metrics.labels("gateway_device_online", device="tank1_oxygen")["profile"] == S10
    assert metrics.value("gateway_device_online", device="basin_chlorine") == 0
    assert metrics.find("gateway_device_online", device="tank2_oxygen") == []  # unknown yet
    assert metrics.value("gateway_poll_lag_seconds", **tank1) == 0.004
    assert metrics.value("gateway_missed_deadlines_total", **tank1) == 3
    assert metrics.value("gateway_unreadable_points", **tank1) == 1


def test_gateway_and_mqtt(server: MetricsServer, state: GatewayState) -> None:
    metrics = scrape(server)
    assert metrics.value("gateway_up") == 1
    assert abs(metrics.value("gateway_start_time_seconds") - time.time()) < 60
    assert metrics.value("gateway_mqtt_connected") == 1
    assert metrics.value("gateway_mqtt_queue_depth") == 0
    assert metrics.value("gateway_mqtt_queue_max") == 1000
    assert metrics.value("gateway_mqtt_dropped_total") == 0
    assert metrics.value("gateway_mqtt_published_total") == 42
    state.mqtt = MqttStatus(enabled=False)
    assert scrape(server).find("gateway_mqtt_connected") == []


def test_every_family_keeps_one_set_of_label_names(server: MetricsServer) -> None:
    for name, rows in scrape(server).families.items():
        by_series: dict[str, set[frozenset[str]]] = {}
        for sample_name, labels, _ in rows:
            by_series.setdefault(sample_name, set()).add(frozenset(labels))
        for series, label_sets in by_series.items():
            assert len(label_sets) == 1, f"{name}: {series} has label sets {label_sets}"


def test_families_mixing_a_unit_label_and_none_fill_it_in() -> None:
    # x_span is nA/unit (a label); a profile-less point of the same name without a unit
    # joins the family with unit="" (Prometheus stores that as no label).
    state = GatewayState()
    state.record(
        [
            sample("basin_chlorine", CL2, "x_span", 60.0, unit="nA/unit"),
            sample("other", "custom-profile", "x_span", 1.5),
        ]
    )
    with MetricsServer(state, host="127.0.0.1", port=0) as server:
        metrics = scrape(server)
    assert metrics.value("gateway_x_span", device="basin_chlorine", unit="nA/unit") == 60.0
    assert metrics.value("gateway_x_span", device="other", unit="") == 1.5


def naming(point: str, unit: str | None, **how: Any) -> ValueNaming:
    found = value_naming(point, unit, **how)
    assert found is not None, point
    return found


def test_value_naming_follows_prometheus_conventions() -> None:
    assert naming("temperature", "°C").family == "gateway_temperature_celsius"
    assert naming("operating_seconds", "s").family == "gateway_operating_seconds"
    # Base units: the value converted from the sensor's unit.
    for point, unit, family, sent, exported in (
        ("cell_current", "nA", "gateway_cell_current_amperes", 152.5, 1.525e-07),
        (
            "current_output_fixed_value",
            "mA",
            "gateway_current_output_fixed_value_amperes",
            4,
            0.004,
        ),
        ("raw_oxygen_amplitude", "µV", "gateway_raw_oxygen_amplitude_volts", 350, 0.00035),
        ("min_response_time", "ms", "gateway_min_response_time_seconds", 20, 0.02),
        ("cip_min_duration", "min", "gateway_cip_min_duration_seconds", 2.5, 150),
        ("pressure", "hPa", "gateway_pressure_pascals", 1013.25, 101325),
        ("compensation_pressure", "mbar", "gateway_compensation_pressure_pascals", 950, 95000),
        (
            "compensation_salinity",
            "mS/cm",
            "gateway_compensation_salinity_siemens_per_metre",
            12.3,
            1.23,
        ),
        (
            "hours_outside_operating_temperature",
            "h",
            "gateway_time_outside_operating_temperature_seconds",
            0.5,
            1800,
        ),
    ):
        found = naming(point, unit)
        assert (found.family, found.convert(sent)) == (family, exported), point
    assert naming("phase_shift", "°").family == "gateway_phase_shift_degrees"  # no base form
    # Counts that are not counters: no _total, no "counter" in the name.
    assert naming("cip_cycles_total", "").family == "gateway_cip_cycles"
    assert naming("measurement_counter", "").family == "gateway_measurements"
    slope = naming("nominal_slope", "nA/ppm")
    assert (slope.family, slope.unit_label, slope.fixed_unit, slope.convert(60)) == (
        "gateway_nominal_slope",
        True,
        "nA/ppm",
        60,
    )
    oxygen = naming("oxygen", None, unit_from=True)
    assert (oxygen.family, oxygen.unit_label, oxygen.from_register) == (
        "gateway_oxygen",
        True,
        True,
    )
    constant = naming("sensor_constant_m", "")
    assert (constant.family, constant.entry) == ("gateway_sensor_constant", ("constant", "m"))
    assert naming("calibration_status", "").family == "gateway_calibration_status"
    assert naming("up", None).family == "gateway_up_value"  # never one of ours
    # Not metrics: a log's entries, and what gateway_device_info's labels carry.
    assert value_naming("logbook_3_oxygen", "", repeat="logbook") is None
    assert value_naming("firmware_version", "") is None


# --- /healthz ------------------------------------------------------------------------------


def test_healthz_ok(server: MetricsServer) -> None:
    reply = fetch(f"http://127.0.0.1:{server.port}/healthz")
    assert (reply.status, reply.content_type) == (200, "application/json")
    body = reply.json()
    assert body["status"] == "ok"
    assert body["reasons"] == []
    open_port = {"port_open": True, "port_problem": None, "port_error": None}
    assert body["buses"] == {
        "line1": {
            **open_port,
            "latency_timer_s": None,
            "devices_online": 1,
            "devices": 2,
            "line_noise": None,
            "no_silence_errors": 0,
        },
        "line2": {
            **open_port,
            "latency_timer_s": None,
            "devices_online": 0,
            "devices": 1,
            "line_noise": None,
            "no_silence_errors": 0,
        },
    }
    assert body["mqtt"]["connected"] is True


def test_healthz_unhealthy_with_reasons(server: MetricsServer, state: GatewayState) -> None:
    state.lines["line2"].port_open = False
    state.mqtt = MqttStatus(
        enabled=True,
        connected=False,
        queue_depth=1000,
        queue_max=1000,
        last_error="connection refused",
    )
    reply = fetch(f"http://127.0.0.1:{server.port}/healthz")
    assert reply.status == 503
    body = reply.json()
    assert body["status"] == "unhealthy"
    assert body["buses"]["line2"]["port_open"] is False
    assert body["reasons"] == [
        "bus line2: port not open (0 failures)",
        "mqtt: not connected and the queue is full (1000/1000): connection refused",
    ]
    assert body["mqtt"]["queue_depth"] == 1000


def test_healthz_buffering_within_bound_is_healthy(
    server: MetricsServer, state: GatewayState
) -> None:
    state.mqtt = MqttStatus(enabled=True, connected=False, queue_depth=10, queue_max=1000)
    assert fetch(f"http://127.0.0.1:{server.port}/healthz").status == 200


def test_unknown_path_is_404(server: MetricsServer) -> None:
    for path in ("/", "/metric", "/healthz/x"):
        assert fetch(f"http://127.0.0.1:{server.port}{path}").status == 404
    assert fetch(f"http://127.0.0.1:{server.port}/metrics?x=1").status == 200


def test_port_in_use_is_a_publish_error(server: MetricsServer, state: GatewayState) -> None:
    second = MetricsServer(state, host="127.0.0.1", port=server.port)
    with pytest.raises(PublishError, match=rf"127\.0\.0\.1:{server.port}"):
        second.start()
    second.stop()  # never started: nothing to do


def test_stop_is_bounded_and_idempotent(state: GatewayState) -> None:
    server = MetricsServer(state, host="127.0.0.1", port=0)
    server.start()
    port = server.port
    assert port != 0
    started = time.monotonic()
    server.stop()
    server.stop()
    assert time.monotonic() - started < 1.0
    with pytest.raises(urllib.error.URLError):
        fetch(f"http://127.0.0.1:{port}/metrics")


def test_silent_and_garbage_clients_neither_block_scrapes_nor_the_stop(
    state: GatewayState,
) -> None:
    """Half-open connections, a burst of them and garbage: scrapes go on, stop stays bounded.

    The server sleeps between connections (no polling loop), so each must be taken as it
    comes: a client that connects and says nothing holds its own thread only.
    """
    server = MetricsServer(state, host="127.0.0.1", port=0)
    server.start()
    silent = [socket.create_connection(("127.0.0.1", server.port)) for _ in range(50)]
    try:
        with socket.create_connection(("127.0.0.1", server.port)) as garbage:
            garbage.sendall(b"\x00\xff NOT HTTP\r\n\r\n")
            garbage.settimeout(5)
            answer = b"".join(iter(lambda: garbage.recv(4096), b""))  # until it closes
            # Not HTTP/1.x, so http.server answers as to HTTP/0.9: the error page alone.
            assert b"Error code: 400" in answer
        for _ in range(3):
            started = time.monotonic()
            assert fetch(f"http://127.0.0.1:{server.port}/healthz").status in (200, 503)
            assert time.monotonic() - started < 1.0
        started = time.monotonic()
        server.stop()
        assert time.monotonic() - started < 1.0  # the silent clients' threads are daemons
    finally:
        for client in silent:
            client.close()


def test_a_failing_scrape_answers_500_and_the_server_keeps_serving(
    server: MetricsServer, state: GatewayState
) -> None:
    def broken() -> list[DeviceHealth]:
        raise RuntimeError("bus task gone")

    state.add_line("line3", LineStats(), broken)
    assert fetch(f"http://127.0.0.1:{server.port}/metrics").status == 500
    del state.health_sources["line3"], state.lines["line3"]
    assert scrape(server).value("gateway_up") == 1


# --- the gateway polling a simulated S10 ---------------------------------------------------


@dataclass(frozen=True)
class Polled:
    """The gateway polling simulated sensors, and its metrics server."""

    metrics: MetricsServer
    simulator: SimulatorServer


@contextlib.asynccontextmanager
async def polled(tmp_path: Path, devices: dict[str, dict[str, Any]]) -> AsyncIterator[Polled]:
    """The gateway polling simulated sensors (by name: profile, address, values)."""
    simulator = SimulatorServer(
        build_bus(parse_settings({"devices": [d | {"animate": False} for d in devices.values()]}))
    )
    port = tmp_path / "ttySIM"
    simulator.open_pty(port)
    config = parse_config(
        f"buses:\n"
        f"  - {{name: line1, port: {port}}}\n"
        "devices:\n"
        + "".join(
            f"  - {{name: {name}, bus: line1, address: {d['address']}, profile: {d['profile']},"
            " poll_interval: 0.5}\n"
            for name, d in devices.items()
        )
        + "mqtt: {enabled: false}\n"
        "prometheus: {enabled: false}\n",  # served below, on a free port
        environ={},
    )
    state = GatewayState()
    stop = asyncio.Event()
    gateway = asyncio.create_task(run(config, [], stop=stop, state=state), name="gateway")
    metrics = MetricsServer(state, host="127.0.0.1", port=0)
    metrics.start()
    try:
        yield Polled(metrics, simulator)
    finally:
        metrics.stop()
        stop.set()
        await asyncio.wait_for(gateway, timeout=10)
        await simulator.close()


@contextlib.asynccontextmanager
async def polled_s10(tmp_path: Path) -> AsyncIterator[MetricsServer]:
    """The gateway polling a simulated S10 (temperature held at 20.25 °C), with metrics."""
    s10 = {"profile": S10, "address": 1, "values": {"temperature": 20.25}}
    async with polled(tmp_path, {"tank1_oxygen": s10}) as rig:
        yield rig.metrics


@pytest.mark.line
async def test_gateway_polling_the_simulator_is_scraped(tmp_path: Path) -> None:
    device = {"bus": "line1", "device": "tank1_oxygen"}
    async with polled_s10(tmp_path) as server:
        # Polled, its identity read, and its oxygen published in the unit its register names.
        series = ("gateway_temperature_celsius", "gateway_device_info", "gateway_oxygen")
        metrics = await scrape_until(server, lambda m: all(m.find(s, **device) for s in series))
    assert metrics.value("gateway_temperature_celsius", **device, profile=S10) == 20.25
    assert metrics.value("gateway_requests_total", **device) > 0
    assert metrics.value("gateway_responses_total", **device) > 0
    assert metrics.value("gateway_request_latency_seconds_count", **device) > 0
    assert metrics.value("gateway_device_online", **device) == 1
    assert metrics.value("gateway_bus_port_open", bus="line1") == 1
    assert metrics.value("gateway_errors_total", **device, kind="timeout") == 0
    assert metrics.labels("gateway_device_info", **device)["serial"] != ""
    # The simulated oxygen is in the unit its unit register names.
    assert metrics.labels("gateway_oxygen", **device)["unit"] in {"%vol", "%sat", "ppm", "mbar"}
    assert not re.search(r"\de\+?3[7-9]\b", metrics.text)


@pytest.mark.line
async def test_identity_is_one_info_series_with_the_sensors_own_values(tmp_path: Path) -> None:
    devices = {
        "tank1_oxygen": {"profile": S10, "address": 1},
        "basin_chlorine": {"profile": CL2, "address": 20},
    }
    async with polled(tmp_path, devices) as rig:
        # Identity is read once, at start: wait for every device's serial.
        metrics = await scrape_until(
            rig.metrics,
            lambda m: (
                {x["device"] for x, _ in m.find("gateway_device_info") if x["serial"]}
                == set(devices)
            ),
        )
        s10, cl2 = rig.simulator.bus.devices[1], rig.simulator.bus.devices[20]
    info = {labels["device"]: labels for labels, _ in metrics.find("gateway_device_info")}
    assert info["tank1_oxygen"] == {
        "bus": "line1",
        "device": "tank1_oxygen",
        "profile": S10,
        "address": "1",
        "serial": s10.get("serial_number"),
        "firmware": s10.get("software_version"),  # S10 6.1: a string, "312.01.02"
        "hardware": f"{s10.get('hardware_version_major')}.{s10.get('hardware_version_minor')}",
    }
    assert info["basin_chlorine"] == {
        "bus": "line1",
        "device": "basin_chlorine",
        "profile": CL2,
        "address": "20",
        "serial": cl2.get("serial_number"),
        "firmware": str(cl2.get("firmware_version")),  # tecLine "Device data": 1503, as sent
        "hardware": str(cl2.get("hardware_version")),
    }
    assert info["basin_chlorine"]["firmware"] == "1503"
    assert {value for _, value in metrics.find("gateway_device_info")} == {1.0}
    # Identity is labels, not gauges (prometheus.legacy_names brings the old gauges back).
    for name in ("gateway_firmware_version", "gateway_hardware_version_major"):
        assert name not in metrics.families


# --- a real Prometheus server --------------------------------------------------------------


@contextlib.contextmanager
def prometheus_server(tmp_path: Path, target_port: int) -> Iterator[str]:
    """Run Prometheus scraping ``127.0.0.1:target_port`` every second; yield its URL."""
    if not Path(PROMETHEUS).is_file():
        pytest.fail(
            f"{PROMETHEUS} is missing: scripts/setup installs the Debian package (as root) 'prometheus' "
            "(apt-get install prometheus)"
        )
    config = tmp_path / "prometheus.yml"
    config.write_text(
        "global: {scrape_interval: 1s, scrape_timeout: 1s, evaluation_interval: 1s}\n"
        "scrape_configs:\n"
        "  - job_name: gateway\n"
        f"    static_configs: [{{targets: ['127.0.0.1:{target_port}']}}]\n"
    )
    port = free_port()
    log = tmp_path / "prometheus.log"
    with log.open("wb") as output:
        process = subprocess.Popen(
            [
                PROMETHEUS,
                f"--config.file={config}",
                f"--storage.tsdb.path={tmp_path / 'tsdb'}",
                f"--web.listen-address=127.0.0.1:{port}",
            ],
            stdout=output,
            stderr=subprocess.STDOUT,
        )
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


async def poll_json(url: str, *, until: Any, timeout_s: float, what: str, log: Path) -> Any:
    """GET ``url`` every 250 ms until ``until(body)`` holds (the server may not be up yet)."""
    deadline = time.monotonic() + timeout_s
    last: object = None
    while time.monotonic() < deadline:
        try:
            reply = await asyncio.to_thread(fetch, url)
        except urllib.error.URLError as exc:  # not listening yet
            last = exc
        else:
            last = reply.body
            if reply.status == 200 and until(reply.json()):
                return reply.json()
        await asyncio.sleep(0.25)
    tail = await asyncio.to_thread(log_tail, log)
    pytest.fail(f"{what} within {timeout_s} s; last answer: {last}\nprometheus log:\n{tail}")


def log_tail(log: Path) -> str:
    return log.read_text(errors="replace")[-2000:] if log.exists() else ""


def target_up(body: Any) -> bool:
    targets = body["data"]["activeTargets"]
    return bool(targets) and all(t["health"] == "up" for t in targets)


def query_value(body: Any) -> float | None:
    result = body["data"]["result"]
    return float(result[0]["value"][1]) if result else None


@pytest.mark.line
async def test_a_real_prometheus_scrapes_the_gateway(tmp_path: Path) -> None:
    log = tmp_path / "prometheus.log"
    async with polled_s10(tmp_path) as server:
        port = server.port
        with prometheus_server(tmp_path, port) as prometheus:
            targets = await poll_json(
                f"{prometheus}/api/v1/targets",
                until=target_up,
                timeout_s=30,
                what="the gateway target was not up",
                log=log,
            )
            query = urllib.parse.urlencode({"query": "gateway_temperature_celsius"})
            body = await poll_json(
                f"{prometheus}/api/v1/query?{query}",
                until=lambda b: query_value(b) == 20.25,
                timeout_s=30,
                what="gateway_temperature_celsius was not stored",
                log=log,
            )
    assert targets["data"]["activeTargets"][0]["lastError"] == ""
    result = body["data"]["result"]
    assert len(result) == 1
    assert result[0]["metric"] == {
        "__name__": "gateway_temperature_celsius",
        "bus": "line1",
        "device": "tank1_oxygen",
        "profile": S10,
        "instance": f"127.0.0.1:{port}",
        "job": "gateway",
    }
    assert math.isclose(float(result[0]["value"][1]), 20.25)
