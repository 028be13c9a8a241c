"""Reloading the config of a running gateway: validated first, only what changed applied.

The gateway runs as users run it (``python -m gateway run --config``, its own process),
against two simulated lines on pseudo-terminals and a real mosquitto; reloads are asked
for with a real SIGHUP and by ``gateway reload``. What a reload kept or changed is read
where a user sees it: ``/metrics`` (a bus that keeps its worker keeps counting its
requests; one rebuilt starts again from zero), ``/healthz`` and the broker's retained
messages.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import re
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from typing import TYPE_CHECKING, Any

import aiohttp
import pytest

from gateway.app.reload import ReloadRequests
from gateway.records import RecordStore, records_path
from tests import sparkplug_decoder
from tests.mqtt_broker import free_port, recording, subscribed
from tests.rigs import simulate_process
from tests.unretrieved import reported_in
from tests.waiting import wait_until

if TYPE_CHECKING:
    from collections.abc import Iterator
    from pathlib import Path

    import aiomqtt

    from tests.mqtt_broker import Broker

LINE = "line: {baudrate: 19200, parity: E, stopbits: 1}\n"
SIM_ONE = LINE + (
    "devices:\n"
    "  - {profile: jumo-digiline-odo-s10, address: 1, animate: false}\n"
    "  - {profile: reiss-m0c, address: 10, animate: false}\n"
)
SIM_TWO = LINE + (
    "devices:\n"
    "  - {profile: jumo-tecline-cl2, address: 3, animate: false}\n"
    "  - {profile: reiss-m3c, address: 4, animate: false}\n"
)


def plant(
    one: Path,
    two: Path,
    *,
    broker: int,
    metrics: int,
    state: Path,
    devices: str,
    extra: str = "",
) -> str:
    return (
        "buses:\n"
        f"  - {{name: line1, port: {one}, baudrate: 19200, parity: E}}\n"
        f"  - {{name: line2, port: {two}, baudrate: 19200, parity: E}}\n"
        "devices:\n"
        "  - {name: oxygen, bus: line1, address: 1, profile: jumo-digiline-odo-s10,"
        " poll_interval: 0.5}\n"
        "  - {name: basin, bus: line1, address: 10, profile: reiss-m0c, poll_interval: 0.5}\n"
        f"{devices}"
        f"mqtt: {{host: 127.0.0.1, port: {broker}, base_topic: gw, discovery: {{enabled: true}}}}\n"
        f"prometheus: {{host: 127.0.0.1, port: {metrics}}}\n"
        f"state_dir: {state}\n"
        f"{extra}"
    )


CL2 = (
    "  - {name: chlorine, bus: line2, address: 3, profile: jumo-tecline-cl2, poll_interval: 0.5}\n"
)
M3C = "  - {name: dioxide, bus: line2, address: 4, profile: reiss-m3c, poll_interval: 0.5}\n"


def scrape(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as response:
        return str(response.read().decode())


def healthz(port: int) -> dict[str, object]:
    """The body of ``/healthz``, healthy (200) or not (503: a device offline for a moment)."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=5) as response:
            body: dict[str, object] = json.loads(response.read())
    except urllib.error.HTTPError as exc:
        body = json.loads(exc.read())
    return body


def sample(text: str, name: str, **labels: str) -> float | None:
    """One sample of ``text`` by name and the labels given (others may be there too)."""
    for line in text.splitlines():
        if not line.startswith(name + "{") and not line.startswith(name + " "):
            continue
        if all(f'{key}="{value}"' in line for key, value in labels.items()):
            return float(line.rsplit(" ", 1)[1])
    return None


def requests_of(text: str, bus: str) -> float:
    """Every request the bus's line has sent (the family's name aside: by its labels)."""
    total = 0.0
    for line in text.splitlines():
        if re.match(r"gateway_requests(_total)?\{", line) and f'bus="{bus}"' in line:
            total += float(line.rsplit(" ", 1)[1])
    return total


WAIT_S = 15.0  # how long a reload's effect may take to show


@pytest.fixture
def lines(tmp_path: Path) -> Iterator[tuple[Path, Path]]:
    (tmp_path / "one").mkdir()
    (tmp_path / "two").mkdir()
    with (
        simulate_process(tmp_path / "one", SIM_ONE) as (one, _),
        simulate_process(tmp_path / "two", SIM_TWO) as (two, _),
    ):
        yield one, two


class Running:
    """The gateway's process on a config file the test edits."""

    def __init__(self, tmp_path: Path, one: Path, two: Path, broker: int) -> None:
        self.metrics = free_port()
        self.state = tmp_path / "state"
        self.config = tmp_path / "gateway.yaml"
        self.lines = (one, two)
        self.broker = broker
        self.extra = ""
        self.process: subprocess.Popen[str] | None = None

    def write(self, devices: str) -> None:
        """The config with line1's two devices and ``devices`` (on line2) after them."""
        one, two = self.lines
        text = plant(
            one,
            two,
            broker=self.broker,
            metrics=self.metrics,
            state=self.state,
            devices=devices,
            extra=self.extra,
        )
        self.config.write_text(text, encoding="utf-8")

    def start(self) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "gateway", "run", "--config", str(self.config), "--no-print"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    def online(self, *devices: str) -> bool:
        try:
            text = scrape(self.metrics)
        except OSError:
            return False
        return all(sample(text, "gateway_device_online", device=d) == 1.0 for d in devices)

    def stop(self) -> str:
        assert self.process is not None
        self.process.send_signal(signal.SIGTERM)
        _, stderr = self.process.communicate(timeout=20)
        return stderr


@pytest.fixture
def gateway(tmp_path: Path, lines: tuple[Path, Path], broker: Broker) -> Iterator[Running]:
    running = Running(tmp_path, *lines, broker.port)
    running.write(CL2 + M3C)
    running.start()
    try:
        wait_until(lambda: running.online("oxygen", "basin", "chlorine", "dioxide"), within_s=30)
        yield running
    finally:
        stderr = running.stop()
        assert "Traceback" not in stderr, stderr
        assert not reported_in(stderr), stderr


@pytest.mark.line
@pytest.mark.broker
def test_a_file_with_a_problem_is_refused_and_the_running_config_stays(gateway: Running) -> None:
    assert gateway.process is not None
    before = scrape(gateway.metrics)
    assert sample(before, "gateway_config_last_reload_successful") == 1.0
    text = gateway.config.read_text(encoding="utf-8")
    gateway.config.write_text(text.replace("address: 10,", "address: 1,"), encoding="utf-8")
    gateway.process.send_signal(signal.SIGHUP)
    wait_until(
        lambda: healthz(gateway.metrics)["config"]["reloads"] == 1,  # type: ignore[index]
        within_s=WAIT_S,
    )
    after = scrape(gateway.metrics)
    assert sample(after, "gateway_config_last_reload_successful") == 0.0
    config = healthz(gateway.metrics)["config"]
    assert isinstance(config, dict)
    # The problem as check-config says it: key path, line, what is wrong.
    assert any(
        p.startswith("devices[1].address (line 6): address 1 is already used")
        for p in config["problems"]
    ), config
    assert gateway.process.poll() is None
    # Nothing was rebuilt: every bus keeps counting its requests where it was.
    time.sleep(1.0)
    later = scrape(gateway.metrics)
    for bus in ("line1", "line2"):
        assert requests_of(later, bus) > requests_of(before, bus)
    assert sample(later, "gateway_config_last_reload_success_timestamp_seconds") == sample(
        before, "gateway_config_last_reload_success_timestamp_seconds"
    )
    # Recorded, with the file's hash and its problem (README: Records).
    [reload] = reloads_recorded(gateway)
    assert reload["result"] == "failed"
    assert reload["data"]["sha256"] == hashlib.sha256(gateway.config.read_bytes()).hexdigest()
    assert any("address 1 is already used" in p for p in reload["data"]["problems"])


def reloads_recorded(gateway: Running) -> list[dict[str, Any]]:
    store = RecordStore(records_path(gateway.state), read_only=True)
    return [dict(r.body) for r in store.records() if r.kind == "reload"]


@pytest.mark.line
@pytest.mark.broker
async def test_an_unchanged_bus_runs_on_and_a_removed_device_leaves_no_trace(
    gateway: Running, broker: Broker
) -> None:
    # The retained topics of the device to be removed exist before, its discovery too.
    async with recording(broker.port, "gw/dioxide/#", name="before") as seen:
        await seen.wait_for("gw/dioxide/availability", "online")
    async with recording(broker.port, "homeassistant/#", name="announced") as announced:
        await asyncio.sleep(1.0)
    assert any("_dioxide" in m.topic and m.payload for m in announced.messages)
    before = scrape(gateway.metrics)
    missed_before = sample(before, "gateway_missed_deadlines_total", device="oxygen")
    # The M3C goes; the tecLine no longer polls its temperature; line1 is as it was.
    gateway.write(
        CL2.replace(
            "poll_interval: 0.5}", "poll_interval: 0.5, points: {temperature: {enabled: false}}}"
        )
    )
    command = [sys.executable, "-m", "gateway", "reload", "--config", str(gateway.config)]
    result = await asyncio.to_thread(
        subprocess.run, command, capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 0, result.stderr
    assert "reloaded: the running gateway applied the config" in result.stderr  # the log
    after = scrape(gateway.metrics)
    assert sample(after, "gateway_config_last_reload_successful") == 1.0
    # line1 kept its worker and its open port: its counters run on, no deadline was missed.
    assert requests_of(after, "line1") >= requests_of(before, "line1")
    assert sample(after, "gateway_missed_deadlines_total", device="oxygen") == missed_before
    # line2 lost a device: the same worker and port go on without it, counters running on.
    assert requests_of(after, "line2") >= requests_of(before, "line2")
    assert sample(after, "gateway_device_online", device="dioxide") is None
    await asyncio.to_thread(wait_until, lambda: gateway.online("chlorine"), within_s=WAIT_S)
    # The removed device's retained messages are gone: a new subscriber gets none.
    await asyncio.sleep(0.5)
    async with recording(broker.port, "gw/dioxide/#", name="after") as left:
        await asyncio.sleep(1.0)
    assert [m for m in left.messages if m.payload] == [], left.messages[:5]
    async with recording(broker.port, "homeassistant/#", name="unannounced") as still:
        await asyncio.sleep(1.0)
    assert [m.topic for m in still.messages if "_dioxide" in m.topic and m.payload] == []
    assert any("_chlorine" in m.topic and m.payload for m in still.messages)  # it stays
    # The tecLine's temperature: neither its entity nor its retained value is left.
    entities = [m.topic for m in still.messages if "_chlorine" in m.topic and m.payload]
    assert not [t for t in entities if "temperature" in t], entities
    assert any("concentration" in t for t in entities), entities  # announced anew
    async with recording(broker.port, "gw/chlorine/#", name="tecline") as tecline:
        await tecline.wait_for("gw/chlorine/concentration")
        await asyncio.sleep(1.0)
    assert [m for m in tecline.messages if m.topic == "gw/chlorine/temperature" and m.payload] == []


@pytest.mark.line
@pytest.mark.broker
def test_gateway_reload_of_a_file_with_a_problem_exits_2_and_the_gateway_says_so_too(
    gateway: Running,
) -> None:
    text = gateway.config.read_text(encoding="utf-8")
    gateway.config.write_text(text + "bogus: 1\n", encoding="utf-8")
    command = [sys.executable, "-m", "gateway", "reload", "--config", str(gateway.config)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=60, check=False)
    assert result.returncode == 2
    assert "bogus (line 12): unknown key 'bogus'" in result.stderr, result.stderr
    assert "not reloaded: the running gateway keeps its config" in result.stderr
    # Told all the same, so that what is watched (log, metrics, /healthz) says so.
    wait_until(
        lambda: healthz(gateway.metrics)["config"]["reloads"] == 1,  # type: ignore[index]
        within_s=WAIT_S,
    )
    assert sample(scrape(gateway.metrics), "gateway_config_last_reload_successful") == 0.0
    assert gateway.online("oxygen", "basin", "chlorine", "dioxide")


@pytest.mark.line
@pytest.mark.broker
def test_an_added_bus_is_started_and_a_removed_one_stopped(gateway: Running) -> None:
    assert gateway.process is not None
    text = gateway.config.read_text(encoding="utf-8")
    gateway.config.write_text(
        text.replace("name: line2,", "name: line3,").replace("bus: line2,", "bus: line3,"),
        encoding="utf-8",
    )
    gateway.process.send_signal(signal.SIGHUP)
    wait_until(
        lambda: healthz(gateway.metrics)["config"]["reloads"] == 1,  # type: ignore[index]
        within_s=WAIT_S,
    )
    wait_until(lambda: gateway.online("chlorine", "dioxide"), within_s=WAIT_S)
    metrics = scrape(gateway.metrics)
    assert requests_of(metrics, "line3") > 0
    assert requests_of(metrics, "line2") == 0  # its line's counters went with it
    assert sample(metrics, "gateway_device_online", device="chlorine", bus="line3") == 1.0
    [reload] = reloads_recorded(gateway)
    assert reload["result"] == "done"
    assert "buses added: line3" in reload["note"]


async def test_a_reload_asked_during_a_reload_is_applied_after_it() -> None:
    requests = ReloadRequests()
    requests.ask()
    await asyncio.wait_for(requests.next(), 1)  # the first begins
    requests.ask()  # asked while it runs
    requests.ask()  # twice: one more reload covers both
    await asyncio.wait_for(requests.next(), 1)
    waiting = asyncio.create_task(requests.next())
    await asyncio.sleep(0.05)
    assert not waiting.done()  # nothing more was asked
    waiting.cancel()


SPARKPLUG = "sparkplug: {enabled: true, group_id: plant, edge_node_id: gw1, birth_wait_s: 0}\n"


@pytest.mark.line
@pytest.mark.broker
async def test_sparkplug_hears_only_the_devices_that_changed(
    tmp_path: Path, lines: tuple[Path, Path], broker: Broker
) -> None:
    """A device removed: its DDEATH; added again: a DBIRTH with aliases never given before.

    The node's own metrics do not change, so there is no NDEATH and no new NBIRTH.
    """
    heard: list[tuple[str, sparkplug_decoder.DecodedPayload]] = []

    def keep(message: aiomqtt.Message) -> None:
        payload = message.payload
        assert isinstance(payload, bytes)
        if "/STATE/" not in str(message.topic):
            heard.append((str(message.topic), sparkplug_decoder.decode(payload)))

    def births(kind: str) -> dict[str, set[int]]:
        return {
            topic.rsplit("/", 1)[1]: {m.alias for m in payload.metrics if m.alias is not None}
            for topic, payload in heard
            if f"/{kind}/" in topic
        }

    running = Running(tmp_path, *lines, broker.port)
    running.extra = SPARKPLUG
    running.write(CL2 + M3C)
    async with subscribed(broker.port, "spBv1.0/plant/#", keep, name="host"):
        running.start()
        try:
            await asyncio.to_thread(
                wait_until,
                lambda: {"oxygen", "basin", "chlorine", "dioxide"} <= set(births("DBIRTH")),
                within_s=30,
            )
            # birth_wait_s 0: a first DBIRTH at once, a second once the units are read.
            # The reloads are judged from when the births have settled.
            settled = len(heard)
            while True:
                await asyncio.sleep(1.5)
                if not [t for t, _ in heard[settled:] if "BIRTH" in t]:
                    break
                settled = len(heard)
            first = births("DBIRTH")
            assert [t for t, _ in heard if "/NBIRTH/" in t] == ["spBv1.0/plant/NBIRTH/gw1"]
            start = len(heard)
            running.write(CL2)
            assert running.process is not None
            running.process.send_signal(signal.SIGHUP)
            await asyncio.to_thread(
                wait_until,
                lambda: any(t.endswith("/DDEATH/gw1/dioxide") for t, _ in heard[start:]),
                within_s=WAIT_S,
            )
            running.write(CL2 + M3C.replace("poll_interval: 0.5", "poll_interval: 1"))
            running.process.send_signal(signal.SIGHUP)
            await asyncio.to_thread(
                wait_until,
                lambda: any(t.endswith("/DBIRTH/gw1/dioxide") for t, _ in heard[start:]),
                within_s=WAIT_S,
            )
            await asyncio.sleep(1.0)
            end = len(heard)
        finally:
            stderr = await asyncio.to_thread(running.stop)
    assert heard[-1][0] == "spBv1.0/plant/NDEATH/gw1"  # at the stop
    after = [topic for topic, _ in heard[start:end]]
    assert not [t for t in after if "/NBIRTH/" in t or "/NDEATH/" in t], after
    # Only the device that changed died and was born again.
    assert {t.rsplit("/", 1)[1] for t in after if "/DDEATH/" in t or "/DBIRTH/" in t} == {"dioxide"}
    reborn = next(
        {m.alias for m in payload.metrics if m.alias is not None}
        for topic, payload in heard[start:]
        if topic.endswith("/DBIRTH/gw1/dioxide")
    )
    ever = set().union(*first.values())
    assert reborn
    assert not reborn & ever, sorted(reborn & ever)[:5]
    assert "Traceback" not in stderr, stderr


PASSWORD = "correct horse battery"  # noqa: S105 - the test gateway's page


def page_section(port: int, **more: object) -> str:
    keys = "".join(f", {key}: {value}" for key, value in more.items())
    return f'web: {{enabled: true, port: {port}, password: "{PASSWORD}"{keys}}}\n'


async def calibration(
    http: aiohttp.ClientSession, url: str, run_id: str, *, past: set[str]
) -> dict[str, object]:
    """The run as the page reads it, once its phase is none of ``past``."""
    async with asyncio.timeout(30):
        while True:
            async with http.get(f"{url}/api/calibrations/{run_id}") as response:
                run: dict[str, object] = await response.json()
            if run["phase"] not in past:
                return run
            await asyncio.sleep(0.2)


async def start_slope(http: aiohttp.ClientSession, url: str) -> tuple[dict[str, str], str]:
    """Sign in and start the tecLine's slope calibration: the session's headers, the run."""
    login = {"name": "ana", "password": PASSWORD}
    async with http.post(f"{url}/api/login", json=login) as response:
        assert response.status == 200, await response.text()
        headers = {"X-CSRF-Token": (await response.json())["csrf"]}
    start = {
        "device": "chlorine",
        "procedure": "slope",
        "inputs": {"reference": 0.5, "samples": 1},
        "password": PASSWORD,  # the start is signed
    }
    async with http.post(f"{url}/api/calibrations", json=start, headers=headers) as response:
        assert response.status == 201, await response.text()
        return headers, str((await response.json())["id"])


def edit_line2(running: Running, web: int, edit: str) -> None:
    """``devices``: the other sensor of line2 polled every second, the page's section changed;
    ``line``: line2's own settings (the simulator's line does not echo: it says so now)."""
    if edit == "devices":
        running.extra = page_section(web, confirm_minutes=9)
        running.write(CL2 + M3C.replace("poll_interval: 0.5", "poll_interval: 1"))
    else:
        text = running.config.read_text(encoding="utf-8")
        edited = re.sub(r"(name: line2, [^}]*)}", r"\1, echo: off}", text)
        running.config.write_text(edited, encoding="utf-8")


@pytest.mark.parametrize("edit", ["devices", "line"])
@pytest.mark.line
@pytest.mark.broker
async def test_a_calibration_under_way_goes_on_through_a_reload_of_its_bus(
    tmp_path: Path, lines: tuple[Path, Path], broker: Broker, edit: str
) -> None:
    """The tecLine's slope calibration waits at its question through a reload of its bus;
    answered after it, it writes.

    ``devices``: the other sensor of its bus is re-planned and the page's section changes:
    the bus keeps its worker and its port (its requests count on), the page its sign-in
    and the run. ``line``: the bus's own settings change: polling pauses, its port opens
    anew, and the run goes on all the same. The tecLine misses no deadline either way.
    """
    web = free_port()
    running = Running(tmp_path, *lines, broker.port)
    running.extra = page_section(web)
    running.write(CL2 + M3C)
    running.start()
    url = f"http://127.0.0.1:{web}"
    try:
        await asyncio.to_thread(
            wait_until, lambda: running.online("chlorine", "dioxide"), within_s=30
        )
        async with aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as http:
            headers, run_id = await start_slope(http, url)
            run = await calibration(http, url, run_id, past={"running"})
            assert run["phase"] == "confirm", run
            before = scrape(running.metrics)
            missed = sample(before, "gateway_missed_deadlines_total", device="chlorine")

            edit_line2(running, web, edit)
            assert running.process is not None
            running.process.send_signal(signal.SIGHUP)
            await asyncio.to_thread(
                wait_until,
                lambda: healthz(running.metrics)["config"]["reloads"] == 1,  # type: ignore[index]
                within_s=WAIT_S,
            )
            after = scrape(running.metrics)
            assert sample(after, "gateway_config_last_reload_successful") == 1.0
            if edit == "devices":
                assert requests_of(after, "line2") >= requests_of(before, "line2")
            assert sample(after, "gateway_missed_deadlines_total", device="chlorine") == missed

            # The rebuilt page knows the session and the run, still at its question.
            run = await calibration(http, url, run_id, past=set())
            assert run["phase"] == "confirm", run
            assert run["mine"] is True
            answer = f"{url}/api/calibrations/{run_id}/answer"
            async with http.post(answer, json={"confirm": True}, headers=headers) as r:
                assert r.status == 200, await r.text()
            run = await calibration(http, url, run_id, past={"confirm", "writing", "running"})
        assert run["phase"] == "done", run
        outcome = run["outcome"]
        assert isinstance(outcome, dict)
        assert outcome["status"] == "calibrated", outcome
        written = [w["point"] for w in outcome["writes"]]
        assert written == ["x_zero", "x_span", "calibration_stamp"], written
        await asyncio.to_thread(
            wait_until, lambda: running.online("chlorine", "dioxide"), within_s=WAIT_S
        )
    finally:
        stderr = running.stop()
    assert "Traceback" not in stderr, stderr
    paused = "line2: polling paused: its settings changed" in stderr
    assert paused is (edit == "line"), stderr[-3000:]
    assert "line1: polling paused" not in stderr
