"""A clock you can trust: dates go into sensors only while the host clock is synchronised.

The kernel of the test host does not hold its clock synchronised (a VM or a container:
``adjtimex`` says ``TIME_ERROR``, maximum error 16 s), and no test may change that. So
the refusals are tested against the real kernel: ``set-clock``, a calibration, a
``…/set`` of a stamp, another master's write on the shared bus are refused with why and
how to fix it, and nothing reaches the simulated sensor. Where the kernel says the
clock is synchronised, the same tests expect the writes to go through (``REFUSED``).
The verdict "synchronised" is tested through the pure function, and the way through
while unsynchronised is the override (``clock.trust_unsynchronised``, in the environment
as ``GATEWAY_CLOCK__TRUST_UNSYNCHRONISED``, which ``tests/conftest.py`` sets for the
other tests and these take away).
"""

from __future__ import annotations

import asyncio
import errno
import json
import subprocess
import sys
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

import aiomqtt
import pytest

from gateway.config import FlashPolicy, check_config
from gateway.control.calibration import calibrate_oxygen_zero, calibrate_slope
from gateway.control.calibration.catalogue import PROCEDURES
from gateway.control.clock_trust import clock_refusal, time_point_touched, time_points
from gateway.control.flash import FlashLedger
from gateway.control.operations import set_clock
from gateway.control.writes import SafeWriter
from gateway.errors import CommandRejectedError
from gateway.profiles import builtin_profiles, get_profile
from gateway.shared.host_clock import (
    MAX_ERROR_LIMIT_US,
    STA_UNSYNC,
    TIME_ERROR,
    TRUST_VARIABLE,
    HostClock,
    KernelClock,
    judge,
    read_kernel_clock,
    synchronised,
    trust_from_environment,
)
from gateway.shared.state import GatewayState
from gateway.wire.codec import DataType
from tests.control.shared_bus.test_shared_bus import TECLINE, _mbap, _raw
from tests.control.shared_bus.test_shared_bus import plant as shared_plant
from tests.control.test_calibration import FakeOperator
from tests.mqtt_broker import free_port, recording
from tests.publish.test_mqtt import gateway, simulated
from tests.rigs import link_rig, link_target, run_gateway, simulate_process, stats_of
from tests.storage_rig import get
from tests.web_rig import CHLORINE, NAMES, PASSWORD, PHONE, browser, sign_in
from tests.web_rig import plant as web_plant

if TYPE_CHECKING:
    from pathlib import Path

    from tests.mqtt_broker import Broker, Recorder
    from tests.rigs import LinkRig


# What the real kernel says now: the refusals are expected exactly when it is unsynchronised.
def _kernel() -> KernelClock | None:
    try:
        return read_kernel_clock()
    except OSError:
        return None  # the gateway cannot ask either: it refuses (and one test fails)


KERNEL = _kernel()
REFUSED = KERNEL is None or not synchronised(KERNEL)
SYNCED = KernelClock(state=0, status=0x2001, max_error_us=12_500, estimated_error_us=300)
WHY = "host clock" if REFUSED else ""
FIX = "clock.trust_unsynchronised: true"
S10, H10, CL2 = 1, 2, 20
SENSORS: list[dict[str, Any]] = [
    {"profile": "jumo-digiline-odo-s10", "address": S10, "animate": False},
    {"profile": "jumo-digiline-odo-h10", "address": H10, "animate": False},
    {"profile": "jumo-tecline-cl2", "address": CL2, "animate": False},
]
TARGETS = [
    link_target("s10", "jumo-digiline-odo-s10", S10),
    link_target("h10", "jumo-digiline-odo-h10", H10),
    link_target("cl2", "jumo-tecline-cl2", CL2),
]
STAMP = datetime(2026, 11, 27, 10, 30)


@pytest.fixture
def untrusted(monkeypatch: pytest.MonkeyPatch) -> None:
    """No override: the kernel's word alone, as on a plant that did not set one."""
    monkeypatch.delenv(TRUST_VARIABLE, raising=False)


# --- the verdict, pure ---------------------------------------------------------------------


def test_synchronised_is_a_maximum_error_below_16_s_as_timedatectl_says() -> None:
    assert synchronised(SYNCED)
    assert synchronised(
        KernelClock(state=0, status=0, max_error_us=15_999_999, estimated_error_us=0)
    )
    boot = KernelClock(
        state=TIME_ERROR, status=STA_UNSYNC, max_error_us=16_000_000, estimated_error_us=16_000_000
    )
    assert not synchronised(boot)
    # chrony without rtcsync keeps STA_UNSYNC set on a clock it keeps: timedatectl says yes.
    chrony = KernelClock(
        state=TIME_ERROR, status=STA_UNSYNC | 0x2000, max_error_us=40_000, estimated_error_us=10
    )
    assert synchronised(chrony)
    status = judge(boot, trust_unsynchronised=False)
    assert (status.synchronised, status.trusted, status.max_error_s) == (False, False, 16.0)
    assert "TIME_ERROR" in status.problem
    assert "maximum error 16 s" in status.problem
    trusted = judge(boot, trust_unsynchronised=True)
    assert (trusted.synchronised, trusted.trusted) == (False, True)
    assert judge(SYNCED, trust_unsynchronised=False).as_dict() == {
        "synchronized": True,
        "trusted": True,
        "trust_unsynchronised": False,
        "max_error_s": 0.0125,
        "estimated_error_s": 0.0003,
        "kernel_state": "TIME_OK",
        "problem": None,
        "fix": None,
    }


def test_a_kernel_that_cannot_be_asked_is_not_trusted_and_the_reason_names_the_call() -> None:
    status = judge(OSError(errno.EPERM, "Operation not permitted"), trust_unsynchronised=False)
    assert not status.trusted
    assert status.max_error_s is None
    assert "adjtimex: EPERM" in status.problem

    def forbidden() -> KernelClock:
        raise OSError(errno.EPERM, "Operation not permitted")

    assert not HostClock(trust_unsynchronised=False, read=forbidden).status().trusted
    assert HostClock(trust_unsynchronised=True, read=forbidden).status().trusted


def test_the_override_is_read_from_the_environment_as_pydantic_reads_the_key() -> None:
    for word in ("true", "True", "1", "yes", "on"):
        assert trust_from_environment({TRUST_VARIABLE: word})
        assert trust_from_environment({TRUST_VARIABLE.lower(): word})
    for word in ("false", "0", "no", "", "maybe"):
        assert not trust_from_environment({TRUST_VARIABLE: word})
    assert not trust_from_environment({})
    assert HostClock(trust_unsynchronised=False).trust_unsynchronised is False


def test_the_dates_each_profile_can_be_written() -> None:
    dated = {p.id: [t.name for t in time_points(p)] for p in builtin_profiles().values()}
    for profile_id, names in dated.items():
        if profile_id.startswith(("jumo-tecline", "reiss")):
            assert names == ["calibration_stamp"], profile_id  # tecLine annex 7.2, 0x020A
        elif profile_id == "jumo-digiline-odo-s10":
            assert names == ["clock"], profile_id  # S10 manual 6.9, 0x2840
        elif profile_id.startswith("jumo-digiline-odo-h"):
            assert names == ["calibration_date"], profile_id  # H10/H20 0x300A
        else:
            assert names == [], profile_id
    tecline, s10 = get_profile("jumo-tecline-cl2"), get_profile("jumo-digiline-odo-s10")
    # X_Zero, X_Span and the stamp in one function 16 reaches the stamp; the two alone do not.
    assert time_point_touched(tecline, 0x0206, 6) is tecline.point("calibration_stamp")
    assert time_point_touched(tecline, 0x0206, 4) is None
    assert time_point_touched(tecline, 0x020B, 1) is tecline.point("calibration_stamp")
    # The history's stamps are read-only: the sensor writes them (annex 7.2).
    assert time_point_touched(tecline, 0x0214, 2) is None
    # The manual's example writes the year alone (S10 2.4.2): a view over the clock.
    clock_year = s10.point("clock_year")
    assert time_point_touched(s10, clock_year.address, clock_year.count) is s10.point("clock")
    assert all(p.dtype in {DataType.DATETIME, DataType.YYMMDDHHMM} for p in time_points(s10))


def test_the_refusal_says_why_what_a_wrong_date_does_and_how_to_fix_it() -> None:
    boot = KernelClock(
        state=TIME_ERROR,
        status=STA_UNSYNC,
        max_error_us=MAX_ERROR_LIMIT_US,
        estimated_error_us=MAX_ERROR_LIMIT_US,
    )
    tecline = get_profile("jumo-tecline-cl2")
    untrusted = HostClock(trust_unsynchronised=False, read=lambda: boot)
    reason = clock_refusal(
        untrusted, "writing calibration_stamp of cl2", tecline.point("calibration_stamp")
    )
    assert reason is not None
    assert reason.startswith(
        "writing calibration_stamp of cl2 refused: the kernel holds the host clock unsynchronised"
    )
    assert "overwrites its history entry 0 instead of adding one" in reason  # annex 7.2
    assert "timedatectl set-ntp true" in reason
    assert "System clock synchronized: yes" in reason
    assert f"{FIX} ({TRUST_VARIABLE}=true)" in reason
    s10 = get_profile("jumo-digiline-odo-s10")
    clock_reason = clock_refusal(untrusted, "set-clock of s10", s10.point("clock"))
    assert clock_reason is not None
    assert "dates its records or logbook entries by it" in clock_reason
    assert clock_refusal(HostClock(trust_unsynchronised=False, read=lambda: SYNCED), "x") is None
    assert clock_refusal(HostClock(trust_unsynchronised=True, read=lambda: boot), "x") is None


# --- the real kernel -----------------------------------------------------------------------


def test_the_kernel_is_read_as_it_is_without_changing_it() -> None:
    assert KERNEL is not None, "adjtimex cannot be read on this host"
    again = read_kernel_clock()
    assert 0 <= KERNEL.state <= TIME_ERROR
    assert again.state == KERNEL.state
    assert HostClock(trust_unsynchronised=False).status().synchronised == synchronised(again)
    if not synchronised(again):
        # kernel/time/ntp.c: an error at the limit is clamped there, STA_UNSYNC set, and
        # adjtimex returns TIME_ERROR: the fields are where the struct says they are.
        assert again.max_error_us == MAX_ERROR_LIMIT_US
        assert again.status & STA_UNSYNC
        assert again.state == TIME_ERROR


# --- the write paths, against the simulator --------------------------------------------------


def ledger_in(tmp_path: Path) -> FlashLedger:
    return FlashLedger(tmp_path / "state" / "flash-writes.sqlite")


def writer(rig: LinkRig, device: str, tmp_path: Path, clock: HostClock | None = None) -> SafeWriter:
    policy = FlashPolicy(allowed=frozenset({"x_zero"}), daily_budget=8)
    return SafeWriter(rig.links[device], policy=policy, ledger=ledger_in(tmp_path), clock=clock)


def frames_to(rig: LinkRig, address: int) -> int:
    return sum(1 for f in rig.server.bus.frame_log if f.device == address)


@pytest.mark.usefixtures("untrusted")
@pytest.mark.line
async def test_a_date_written_through_the_write_path_is_refused_before_the_bus(
    tmp_path: Path,
) -> None:
    async with link_rig(tmp_path, SENSORS, TARGETS) as rig:
        cl2, s10, h10 = (writer(rig, name, tmp_path) for name in ("cl2", "s10", "h10"))
        attempts = [
            (cl2, "calibration_stamp", STAMP),
            (s10, "clock", datetime(2026, 11, 27, 10, 30, 5, tzinfo=UTC)),
            (s10, "clock_year", 2026),
            (h10, "calibration_date", datetime(2026, 11, 27, 10, 30, 5, tzinfo=UTC)),
        ]
        for target, name, value in attempts:
            if REFUSED:
                with pytest.raises(CommandRejectedError, match=WHY) as refused:
                    await target.set(target.point(name), value, explicit=True)
                assert FIX in refused.value.reason
            else:
                assert (await target.set(target.point(name), value, explicit=True)).written
        if REFUSED:
            assert [frames_to(rig, a) for a in (S10, H10, CL2)] == [0, 0, 0]
        # A point that is not a date is not the clock's business.
        done = await cl2.set(cl2.point("x_zero"), 1.5)
        assert done.written
        assert [(w.address, w.function) for w in rig.writes(CL2)][-1] == (0x0206, 16)


@pytest.mark.usefixtures("untrusted")
@pytest.mark.line
async def test_a_synchronised_clock_or_the_override_lets_the_stamp_through(tmp_path: Path) -> None:
    async with link_rig(tmp_path, SENSORS, TARGETS) as rig:
        synced = writer(
            rig, "cl2", tmp_path, HostClock(trust_unsynchronised=False, read=lambda: SYNCED)
        )
        done = await synced.set(synced.point("calibration_stamp"), STAMP, explicit=True)
        assert (done.written, done.value) == (True, STAMP)
        override = writer(rig, "cl2", tmp_path, HostClock(trust_unsynchronised=True))
        later = datetime(2026, 11, 27, 10, 31)
        assert (
            await override.set(override.point("calibration_stamp"), later, explicit=True)
        ).written
        # 2611271030 and 2611271031 (YYMMDDHHMM, high word first, tecLine 2.6.2).
        assert [w.values for w in rig.writes(CL2)] == [
            divmod(2611271030, 0x10000),
            divmod(2611271031, 0x10000),
        ]
        assert rig.device(CL2).get("calibration_stamp") == later


@pytest.mark.usefixtures("untrusted")
@pytest.mark.line
async def test_set_clock_is_refused_before_it_reads_anything(tmp_path: Path) -> None:
    async with link_rig(tmp_path, SENSORS, TARGETS) as rig:
        for name, address in (("s10", S10), ("h10", H10)):
            target = writer(rig, name, tmp_path)
            if not REFUSED:
                await set_clock(target, now=datetime.now(UTC))
                continue
            with pytest.raises(
                CommandRejectedError, match=f"set-clock of {name} refused"
            ) as refused:
                await set_clock(target, now=datetime.now(UTC))
            assert FIX in refused.value.reason
            assert frames_to(rig, address) == 0
        trusted = writer(rig, "s10", tmp_path, HostClock(trust_unsynchronised=True))
        setting = await set_clock(trusted, now=datetime.now(UTC))
        assert setting.after is not None
        assert abs(setting.offset_after_s or 0.0) <= 1.0


@pytest.mark.usefixtures("untrusted")
@pytest.mark.line
async def test_a_calibration_is_refused_before_it_reads_or_asks(tmp_path: Path) -> None:
    async with link_rig(tmp_path, SENSORS, TARGETS) as rig:
        rig.device(CL2).hold("cell_current", 76.5)
        writes = {p.id: p for p in PROCEDURES if p.writes}
        for procedure_id, device, address, given in (
            ("slope", "cl2", CL2, {"reference": "0.5"}),
            ("nominal", "cl2", CL2, {}),
            ("oxygen_zero", "h10", H10, {}),
        ):
            procedure = writes[procedure_id]
            operator = FakeOperator()
            target = writer(rig, device, tmp_path)
            if not REFUSED:
                continue
            with pytest.raises(CommandRejectedError, match=WHY):
                await procedure.run(target, operator, procedure.parse(given), when=STAMP)
            assert (operator.steps, operator.questions) == ([], [])  # told before anything
            assert frames_to(rig, address) == 0
        # The flows themselves (as a front end that skips the catalogue would run them):
        # refused at the preflight, before the question and before X_Zero and X_Span.
        if REFUSED:
            operator = FakeOperator()
            with pytest.raises(CommandRejectedError, match=WHY):
                await calibrate_slope(
                    writer(rig, "cl2", tmp_path), operator, reference=0.5, when=STAMP
                )
            assert operator.questions == []
            with pytest.raises(CommandRejectedError, match=WHY):
                await calibrate_oxygen_zero(
                    writer(rig, "h10", tmp_path), FakeOperator(), when=datetime.now(UTC)
                )
            assert rig.writes(CL2) == []
            assert rig.writes(H10) == []  # not even the calibration mode (0x3009)
        trusted = writer(rig, "cl2", tmp_path, HostClock(trust_unsynchronised=True))
        outcome = await writes["nominal"].run(
            trusted, FakeOperator(), writes["nominal"].parse({}), when=STAMP
        )
        assert outcome.ok, outcome.failed_checks
        assert [w.address for w in rig.writes(CL2)] == [0x0208, 0x0206, 0x020A]  # annex 7.5.1


# --- the running gateway: MQTT, /healthz, /metrics, the page, the shared bus ------------------


def gateway_config(tmp_path: Path, broker_port: int, metrics_port: int, web_port: int) -> str:
    return (
        f"buses:\n  - {{name: line1, port: {tmp_path / 'ttySIM'}}}\n"
        "devices:\n"
        f"  - {{name: aeration, bus: line1, address: {S10}, profile: jumo-digiline-odo-s10, poll_interval: 0.5}}\n"
        f"  - {{name: cl2, bus: line1, address: {CL2}, profile: jumo-tecline-cl2, poll_interval: 0.5}}\n"
        f"mqtt: {{host: 127.0.0.1, port: {broker_port}, base_topic: gw, reconnect_max_s: 1}}\n"
        f"prometheus: {{host: 127.0.0.1, port: {metrics_port}}}\n"
        f"web: {{enabled: true, host: 127.0.0.1, port: {web_port}}}\n"
        f"state_dir: {tmp_path / 'state'}\n"
    )


async def result_of(client_topic: str, payload: str, seen: Recorder, port: int) -> dict[str, Any]:
    result = f"{client_topic}/result"
    before = len(seen.on(result))
    async with aiomqtt.Client("127.0.0.1", port, identifier="plant-system") as client:
        await client.publish(client_topic, payload, qos=1)
        await seen.wait_for(result, skip=before, within_s=15)
    document: dict[str, Any] = json.loads(seen.on(result)[before])
    return document


async def http_json(url: str) -> dict[str, Any]:
    status, body = await asyncio.to_thread(get, url)
    assert status == 200, body
    parsed: dict[str, Any] = json.loads(body)
    return parsed


async def scrape(port: int) -> dict[str, float]:
    _, text = await asyncio.to_thread(get, f"http://127.0.0.1:{port}/metrics")
    return {
        line.split()[0]: float(line.split()[1])
        for line in text.splitlines()
        if line.startswith("gateway_clock_")
    }


@pytest.mark.usefixtures("untrusted")
@pytest.mark.line
@pytest.mark.broker
async def test_the_running_gateway_refuses_dates_and_says_so_everywhere(
    tmp_path: Path, broker: Broker
) -> None:
    metrics_port, web_port = free_port(), free_port()
    config = gateway_config(tmp_path, broker.port, metrics_port, web_port)
    async with (
        simulated(tmp_path, SENSORS) as server,
        recording(broker.port, "gw/#") as seen,
        gateway(config) as state,
    ):
        await seen.wait_for("gw/cl2/availability", "online")
        stamp = await result_of(
            "gw/cl2/calibration_stamp/set",
            '{"value": "2026-11-27T10:30", "id": "s1"}',
            seen,
            broker.port,
        )
        clock = await result_of("gw/aeration/command/set_clock", '{"id": "c1"}', seen, broker.port)
        health = await http_json(f"http://127.0.0.1:{metrics_port}/healthz")
        metrics = await scrape(metrics_port)
        page = await http_json(f"http://127.0.0.1:{web_port}/api/state")
        points = (await http_json(f"http://127.0.0.1:{web_port}/api/devices/cl2"))["points"]
        assert state.clock.status().trusted is not REFUSED
    writes = [w for address in (S10, CL2) for w in server.bus.devices[address].write_log]
    if REFUSED:
        for refused in (stamp, clock):
            assert refused["status"] == "error", refused
            assert "host clock" in refused["reason"]
            assert FIX in refused["reason"]
        assert "calibration_stamp of cl2 refused" in stamp["reason"]
        assert "set-clock of aeration refused" in clock["reason"]
        assert writes == []
    else:
        assert (stamp["status"], clock["status"]) == ("ok", "ok")
    # /healthz says it, but stays ok: a restart cannot synchronise a clock.
    assert health["status"] == "ok", health["reasons"]
    assert health["clock"]["synchronized"] is not REFUSED
    assert health["clock"]["trusted"] is not REFUSED
    if REFUSED:  # the kernel holds an unsynchronised clock's error at the limit
        assert health["clock"]["max_error_s"] == MAX_ERROR_LIMIT_US / 1e6
        assert metrics["gateway_clock_max_error_seconds"] == MAX_ERROR_LIMIT_US / 1e6
        assert FIX in health["clock"]["fix"]
        assert "unsynchronised" in health["clock"]["problem"]
    assert metrics["gateway_clock_synchronized"] == float(not REFUSED)
    assert metrics["gateway_clock_trusted"] == float(not REFUSED)
    same = ("synchronized", "trusted", "trust_unsynchronised", "kernel_state", "problem", "fix")
    assert {k: page["clock"][k] for k in same} == {k: health["clock"][k] for k in same}
    stamp_point = next(p for p in points if p["name"] == "calibration_stamp")
    if REFUSED:
        assert stamp_point["writable"] is False
        assert stamp_point["refused"] == "a date, and the host clock is not synchronised"


@pytest.mark.parametrize("override", [False, True], ids=["unsynchronised", "trusted"])
@pytest.mark.line
async def test_another_masters_stamp_write_waits_for_a_trusted_clock(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, *, override: bool
) -> None:
    monkeypatch.delenv(TRUST_VARIABLE, raising=False)
    if override:
        monkeypatch.setenv(TRUST_VARIABLE, "true")
    grant = (
        "shared_bus:\n"
        "  listen: [{host: 127.0.0.1, port: 0}]\n"
        "  clients:\n"
        "    - name: scada\n"
        "      networks: [127.0.0.1/32]\n"
        "      writes:\n"
        "        - {device: cl2, registers: ['0x0206-0x020B']}\n"
    )
    async with shared_plant(tmp_path, grant) as p:
        # Function 16: the stamp 2611271030 at 0x020A, high word first.
        high, low = divmod(2611271030, 0x10000)
        pdu = bytes.fromhex("10020A000204") + high.to_bytes(2, "big") + low.to_bytes(2, "big")
        answer = await _raw(p.tcp_port, _mbap(7, TECLINE, pdu))
        # X_Zero alone (0x0206, float 0.0) is no date: the clock has no say in it.
        x_zero = await _raw(p.tcp_port, _mbap(8, TECLINE, bytes.fromhex("100206000204") + bytes(4)))
        client = p.state.shared_bus.clients["scada"]
        stamps = [w for w in p.device(TECLINE).write_log if w.address == 0x020A]
    assert x_zero[7:] == bytes.fromhex("100206" + "0002")
    if REFUSED and not override:
        assert answer[7:] == bytes((0x90, 0x01))  # exception 01, as for a spent flash budget
        assert client.refused["clock_unsynchronised"] == 1
        assert stamps == []
    else:
        assert answer[7:] == bytes.fromhex("10020A0002")
        assert [w.values for w in stamps] == [(high, low)]


# --- the config key ------------------------------------------------------------------------


CONFIG = """buses:
  - {name: line1, port: /dev/ttyUSB0}
devices:
  - {name: cl2, bus: line1, address: 20, profile: jumo-tecline-cl2}
clock:
  trust_unsynchronised: true
"""


def test_check_config_knows_the_clock_key(tmp_path: Path) -> None:
    path = tmp_path / "gateway.yaml"
    path.write_text(CONFIG, encoding="utf-8")
    assert check_config(path, environ={}) == []
    result = subprocess.run(
        [sys.executable, "-m", "gateway", "check-config", str(path)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    path.write_text(CONFIG.replace("unsynchronised", "unsynchronized"), encoding="utf-8")
    (problem,) = check_config(path, environ={})
    assert (problem.key, problem.line) == ("clock.trust_unsynchronized", 6)
    path.write_text(CONFIG.replace("true", "sometimes"), encoding="utf-8")
    (problem,) = check_config(path, environ={})
    assert (problem.key, problem.line) == ("clock.trust_unsynchronised", 6)


def test_the_state_of_a_gateway_holds_its_host_clock(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(TRUST_VARIABLE, "true")
    state = GatewayState()
    assert state.clock.trust_unsynchronised
    assert state.snapshot().clock is state.clock  # asked at each read, never copied


# --- the page, in a real browser -------------------------------------------------------------


@pytest.mark.usefixtures("untrusted")
@pytest.mark.line
@pytest.mark.browser
async def test_the_page_says_the_clock_is_not_synchronised_and_offers_no_date_to_write(
    tmp_path: Path,
) -> None:
    async with web_plant(tmp_path) as running, browser() as chromium:
        page = await chromium.new_page(viewport=PHONE)
        await page.goto(running.url)
        await page.locator("section[data-device]").first.wait_for()
        note = page.locator("#clock-note")
        if not REFUSED:
            assert await note.count() == 0
            return
        await note.wait_for()
        text = await note.inner_text()
        assert "The host clock is not synchronised" in text
        assert "refused" in text
        assert "timedatectl set-ntp true" in text
        assert FIX in text
        assert await note.get_attribute("role") == "alert"
        # The long variable name wraps: nothing scrolls sideways on the phone.
        assert await page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
        # The register map offers no date for writing, and says why.
        await sign_in(page, running.url)
        await page.goto(f"{running.url}#/device/{NAMES[CHLORINE]}")
        below = page.locator("tr[data-write-row='calibration_stamp']")
        await below.wait_for()
        text = await below.inner_text()
        assert "Not writable: a date, and the host clock is not synchronised" in text
        assert await below.locator("input, button").count() == 0
        # A point that is no date keeps its own reason (X_Zero: flash, not allowed here).
        x_zero = await page.locator("tr[data-write-row='x_zero']").inner_text()
        assert "flash, not in flash_writes" in x_zero
        # A calibration started from the page is refused at once, with the reason.
        await page.goto(f"{running.url}#/calibrate/{NAMES[CHLORINE]}/nominal")
        await page.fill("#sign-password", PASSWORD)  # the start is signed
        await page.click("#start")
        await page.locator("#phase[data-phase='refused']").wait_for(timeout=10_000)
        result = " ".join((await page.locator("#result").inner_text()).split())
        assert "the nominal calibration of pool_chlorine refused" in result
        assert FIX in result
    assert running.writes(CHLORINE) == []


# --- the command line ----------------------------------------------------------------------


@pytest.mark.usefixtures("untrusted")
@pytest.mark.line
def test_the_command_line_refuses_set_clock_and_a_calibration_with_exit_2(tmp_path: Path) -> None:
    simulated = (
        "line: {baudrate: 19200, parity: E, stopbits: 1}\n"
        "devices:\n"
        f"  - {{profile: jumo-digiline-odo-s10, address: {S10}}}\n"
        f"  - {{profile: jumo-tecline-cl2, address: {CL2}}}\n"
    )
    line = ("--baudrate", "19200", "--parity", "E")
    with simulate_process(tmp_path, simulated) as (port, stats):
        at = ("--port", str(port), *line)
        clock = run_gateway(
            "set-clock",
            *at,
            "--address",
            str(S10),
            "--profile",
            "jumo-digiline-odo-s10",
            cwd=tmp_path,
        )
        nominal = run_gateway(
            "calibrate",
            "nominal",
            *at,
            "--address",
            str(CL2),
            "--profile",
            "jumo-tecline-cl2",
            "-y",
            cwd=tmp_path,
        )
        written = [w for d in stats_of(stats)["devices"].values() for w in d["writes"]]
    if not REFUSED:
        assert (clock.returncode, nominal.returncode) == (0, 0), clock.stderr + nominal.stderr
        return
    for refused in (clock, nominal):
        assert refused.returncode == 2, refused.stdout + refused.stderr
        text = " ".join((refused.stdout + refused.stderr).split())  # the terminal's wrapping
        assert "host clock" in text
        assert "trust_unsynchronised" in text
    assert written == []
