"""Sensor care on the page: ``/api/care`` and the care view in a real browser (headless chromium).

The care book holds real reports: each device's records go through the codec as a poll
would decode them (values encoded to registers and back) and into
:meth:`CareBook.observe`, assessed at a fixed time. The records are worked out by hand: a
tecLine calibrated weekly at 80, 74, 68, 62 and 56 % of its nominal slope, its last
calibration nine days ago (due two days ago); a Reiss serviced too late (25 %); a tecLine
due tomorrow; an H20 never calibrated with its cap half used; an S10; an H10 whose records
were not read yet. The last test runs the whole gateway on the simulator and follows the
care view's calibration link to the page's own calibration flow.
"""

from __future__ import annotations

import contextlib
import time
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, Any, Final

import aiohttp
import pytest

from gateway.care import CareBook, care_order, resolve
from gateway.config import WebConfig
from gateway.line.samples import Quality, Sample
from gateway.profiles import get_profile
from gateway.shared.state import DeviceInfo, GatewayState
from gateway.web import WebServer
from gateway.wire import codec, encoding
from tests.mqtt_broker import free_port
from tests.web_rig import CHLORINE, NAMES, PHONE, browser, plant

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Mapping
    from pathlib import Path

    from playwright.async_api import Page

pytestmark = pytest.mark.timeout(120)

NOW: Final = datetime(2026, 11, 26, 10, 0, tzinfo=UTC)  # a Thursday
NOMINAL_NA_PER_PPM: Final = 22.0  # tecLine annex 7.5.1's example
TECLINE: Final = "jumo-tecline-cl2"
REISS: Final = "reiss-m0c"
H10: Final = "jumo-digiline-odo-h10"
H20: Final = "jumo-digiline-odo-h20"
S10: Final = "jumo-digiline-odo-s10"
# Most urgent first: maintenance, unknown (not read yet), due (by date, then none), due soon, ok.
ORDER: Final = [
    ("basin_chlorine", "maintenance"),
    ("digester_oxygen", "unknown"),
    ("pool_chlorine", "due"),
    ("fermenter_oxygen", "due"),
    ("spa_chlorine", "due_soon"),
    ("outlet_oxygen", "ok"),
]


def _decoded(profile_id: str, point: str, value: object) -> codec.Decoded:
    """``value`` as a poll decodes it: encoded to the point's registers and back."""
    fmt = get_profile(profile_id).point(point).format
    registers = () if value is None else encoding.encode(fmt, value)
    return codec.decode(fmt, (*registers, *(0,) * (fmt.count - len(registers))))


def _samples(device: str, profile_id: str, values: Mapping[str, object]) -> list[Sample]:
    return [
        Sample(
            bus="basin",
            device=device,
            profile=profile_id,
            point=point,
            value=_decoded(profile_id, point, value),  # type: ignore[arg-type]
            fault=None,
            unit=None,
            quality=Quality.GOOD,
            monotonic=time.monotonic(),
            time=NOW,
            group="diagnostics",
        )
        for point, value in values.items()
    ]


def _amperometric(ratios: list[float], last: datetime) -> dict[str, object]:
    """The records of a cell calibrated weekly at ``ratios`` of nominal, oldest first."""
    history: list[tuple[float, datetime | None]] = [
        (ratio * NOMINAL_NA_PER_PPM, last - timedelta(weeks=age))
        for age, ratio in enumerate(reversed(ratios))
    ]
    history += [(0.0, None)] * (5 - len(history))
    stamp = last.replace(tzinfo=None)  # the sensor's stamp carries no zone
    values: dict[str, object] = {
        "x_zero": 0.0,
        "x_span": history[0][0],
        "calibration_stamp": stamp,
        "nominal_slope": NOMINAL_NA_PER_PPM,
        "unit": "mg_per_l",
    }
    for index, (span, when) in enumerate(history):
        values[f"history_{index}_x_zero"] = 0.0
        values[f"history_{index}_x_span"] = span
        values[f"history_{index}_stamp"] = None if when is None else when.replace(tzinfo=None)
    return values


def _never_calibrated_h20() -> dict[str, object]:
    values: dict[str, object] = {
        "operating_seconds": 90 * 86400,
        "sensor_replacement_counter": 1,
        "measurement_counter": 50_000,
        "measurement_counter_max": 100_000,
        "cip_cycles_since_calibration": 0,
        "sip_cycles_since_calibration": 0,
        "hours_outside_operating_temperature": 0.0,
        "error_register": 0,
        "status": 0,
    }
    for index in range(1, 11):
        values |= {
            f"logbook_{index}_entry_type": "none",
            f"logbook_{index}_manual_change": "manual",
            f"logbook_{index}_rating": "none",
            f"logbook_{index}_operating_seconds": 0,
            f"logbook_{index}_date": None,
            f"logbook_{index}_sensor_replacement_counter": 0,
            f"logbook_{index}_phase": 0.0,
        }
    return values


def _care_state() -> GatewayState:
    """Six devices care follows (one not read yet) and one it does not."""
    state = GatewayState(care=CareBook(clock=lambda: NOW, zone=UTC))
    devices = {
        "pool_chlorine": (
            TECLINE,
            _amperometric([0.80, 0.74, 0.68, 0.62, 0.56], NOW - timedelta(days=9)),
        ),
        "basin_chlorine": (REISS, _amperometric([0.25], NOW - timedelta(days=2))),
        "spa_chlorine": (TECLINE, _amperometric([0.90], datetime(2026, 11, 20, 8, 0, tzinfo=UTC))),
        "fermenter_oxygen": (H20, _never_calibrated_h20()),
        "outlet_oxygen": (
            S10,
            {"operating_seconds": 86400, "commissioning_date": NOW, "status": 0},
        ),
        "digester_oxygen": (H10, None),  # its records not read yet
    }
    for address, (name, (profile_id, values)) in enumerate(devices.items(), start=1):
        profile = get_profile(profile_id)
        # The points polled: those given (the H10 later, as the H20's); the rest switched off.
        polled = set(values if values is not None else _never_calibrated_h20())
        info = DeviceInfo(bus="basin", name=name, profile=profile_id, address=address, intervals={})
        state.add_device(info)
        rules = resolve(profile, [])
        state.care.add_device(bus="basin", device=name, profile=profile, rules=rules, polled=polled)
        if values is not None:
            state.care.observe(_samples(name, profile_id, values))
    # Care off for it (an `enabled: false`): not on the care view at all.
    state.add_device(
        DeviceInfo(bus="basin", name="lab_chlorine", profile=TECLINE, address=9, intervals={})
    )
    state.care.add_device(
        bus="basin", device="lab_chlorine", profile=get_profile(TECLINE), rules=None, polled=()
    )
    return state


@contextlib.asynccontextmanager
async def _page_server(state: GatewayState) -> AsyncIterator[str]:
    """The page over ``state``, listening on loopback; its URL."""
    config = WebConfig.model_validate({"enabled": True, "port": free_port()})
    server = WebServer(config, state, {}, event_interval_s=0.2)
    await server.start()
    try:
        yield server.url
    finally:
        await server.stop()


async def _get(url: str) -> Any:
    async with aiohttp.ClientSession() as client, client.get(url) as response:
        assert response.status == 200
        return await response.json()


async def test_api_care_sends_every_followed_devices_document_most_urgent_first() -> None:
    state = _care_state()
    async with _page_server(state) as url:
        documents = await _get(f"{url}api/care")
    assert [(d["device"], d["state"]) for d in documents] == ORDER
    by_name = {d["device"]: d for d in documents}
    # The reports' own documents, in care's own order, with what the page adds.
    reports = care_order(state.care.reports())
    assert [r.device for r in reports] == [n for n, _ in ORDER if n != "digester_oxygen"]
    for report in reports:
        added = {"kind": report.kind, "calibration": by_name[report.device]["calibration"]}
        assert by_name[report.device] == report.as_dict() | added
    pool = by_name["pool_chlorine"]
    # The care package's words (hand-computed: 9 days since, weekly; 56 % falling 6 % a week
    # crosses 30 % 4.3 weeks after the last calibration).
    assert pool["reasons"][0] == (
        "check the calibration: overdue for 2 days, due Tue 24 Nov 2026 "
        "(last Tue 17 Nov 2026, weekly)"
    )
    assert "slope 56% of nominal" in pool["reasons"]
    assert any("slope falling 6" in r and "Thu 17 Dec 2026" in r for r in pool["reasons"])
    assert pool["last_calibration"] == "2026-11-17T10:00:00+00:00"
    assert pool["due"] == "2026-11-24T10:00:00+00:00"
    assert pool["slope_ratio"] == pytest.approx(0.56, abs=1e-4)
    assert pool["slope_trend"]["per_week"] == pytest.approx(-0.06, abs=1e-4)
    assert pool["kind"] == "amperometric"
    assert pool["calibration"] == {"procedure": "slope", "title": "Slope (tecLine/Reiss)"}
    assert by_name["basin_chlorine"]["reasons"][0].startswith("slope 25% of nominal, below 30%")
    assert by_name["spa_chlorine"]["reasons"][0] == (
        "check the calibration by Fri 27 Nov 2026 (last Fri 20 Nov 2026, weekly)"
    )
    fermenter = by_name["fermenter_oxygen"]
    assert fermenter["reasons"][0] == "never calibrated: the calibration logbook is empty"
    assert fermenter["cap_usage"] == 0.5
    assert fermenter["calibration"]["procedure"] == "oxygen_end_value"
    # Not read yet: unknown, saying so, with the calibration its family offers.
    digester = by_name["digester_oxygen"]
    assert digester["reasons"] == ["records not read yet"]
    assert digester["assessed_at"] is None
    assert digester["kind"] == "optical_hygienic"
    assert digester["calibration"]["procedure"] == "oxygen_end_value"
    assert by_name["outlet_oxygen"]["calibration"] is None  # the S10 offers none
    assert "lab_chlorine" not in by_name


_MEASURE = """() => {
  const width = document.documentElement.clientWidth;
  const broken = [], outside = [];
  for (const v of document.querySelectorAll("#care .nowrap")) {
    const lines = new Set([...v.getClientRects()].filter((r) => r.width > 0).map((r) => Math.round(r.top)));
    if (lines.size > 1) broken.push(v.textContent);
  }
  for (const c of document.querySelectorAll("#care a, #care .badge, header a")) {
    const r = c.getBoundingClientRect();
    if (r.left < 0 || r.right > width) outside.push(c.textContent);
  }
  return {broken, outside, scroll: document.documentElement.scrollWidth};
}"""


async def _cards(page: Page) -> list[tuple[str | None, str | None]]:
    cards = page.locator("#care section.card")
    return [
        (
            await cards.nth(i).get_attribute("data-device"),
            await cards.nth(i).get_attribute("data-state"),
        )
        for i in range(await cards.count())
    ]


@pytest.mark.browser
async def test_the_care_view_shows_each_devices_state_reasons_and_calibration_link(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    state = _care_state()
    async with _page_server(state) as url, browser() as chromium:
        page = await chromium.new_page(viewport=PHONE, timezone_id="UTC")
        await page.goto(url)
        await page.click("#nav-care")
        await page.locator("#care section.card").first.wait_for()
        assert await _cards(page) == ORDER
        assert await page.locator("#nav-care").get_attribute("aria-current") == "page"
        # Each card: its state's badge, and every reason of its document as a sentence.
        documents = await page.evaluate("fetch('/api/care').then((r) => r.json())")
        for document in documents:
            card = page.locator(f"#care section[data-device='{document['device']}']")
            badge = (await card.locator(".badge").inner_text()).lower()
            assert badge == document["state"].replace("_", " ")
            reasons = await card.locator("ul.reasons li").all_text_contents()
            assert reasons == document["reasons"]
        pool = page.locator("#care section[data-device='pool_chlorine']")
        figures = await pool.locator(".care-figures").inner_text()
        assert figures.startswith("Calibration due since Tue 24 Nov")
        assert "Slope 56 % of nominal and falling 6 % a week: membrane and electrolyte" in figures
        link = pool.locator("a[data-calibrate]")
        assert await link.get_attribute("href") == "#/calibrate/pool_chlorine/slope"
        # The badge's colour is its state's: orange for due, red for maintenance.
        colours = await page.evaluate(
            """() => Object.fromEntries([...document.querySelectorAll("#care section.card")].map(
                (c) => [c.dataset.state, getComputedStyle(c.querySelector(".badge")).color]))"""
        )
        assert colours["due"] == "rgb(194, 65, 12)"
        assert colours["maintenance"] == "rgb(180, 35, 24)"
        assert colours["ok"] == "rgb(26, 127, 55)"
        assert len(set(colours.values())) == 5
        spa = page.locator("#care section[data-device='spa_chlorine'] .care-figures")
        assert (await spa.inner_text()).startswith("Calibrate by Fri 27 Nov")
        basin = page.locator("#care section[data-device='basin_chlorine']")
        assert "Slope 25% of nominal, below 30%" in await basin.inner_text()  # drawn capitalised
        assert "below the 30 % limit" in await basin.locator(".care-figures").inner_text()
        fermenter = page.locator("#care section[data-device='fermenter_oxygen']")
        assert "Cap 50 % used." in await fermenter.inner_text()
        href = await fermenter.locator("a[data-calibrate]").get_attribute("href")
        assert href == "#/calibrate/fermenter_oxygen/oxygen_end_value"
        digester = page.locator("#care section[data-device='digester_oxygen']")
        assert (await digester.locator(".badge").inner_text()).lower() == "unknown"
        assert "Records not read yet" in await digester.inner_text()
        outlet = page.locator("#care section[data-device='outlet_oxygen']")
        assert await outlet.locator("a[data-calibrate]").count() == 0
        # On a phone: no date or percentage broken, nothing off the screen.
        measured = await page.evaluate(_MEASURE)
        assert measured["broken"] == []
        assert measured["outside"] == []
        assert measured["scroll"] <= PHONE["width"]
        shots = tmp_path_factory.getbasetemp() / "web-screenshots"
        shots.mkdir(exist_ok=True)
        await page.screenshot(path=shots / "care-360.png", full_page=True)
        # The H10's records arrive: the open view follows (the overview's care_version).
        state.care.observe(_samples("digester_oxygen", H10, _never_calibrated_h20()))
        read = page.locator("#care section[data-device='digester_oxygen'][data-state='due']")
        await read.wait_for(timeout=10_000)
        assert "Never calibrated" in await read.inner_text()


@pytest.mark.line
@pytest.mark.browser
async def test_on_the_running_gateway_the_care_link_opens_the_slope_calibration(
    tmp_path: Path,
) -> None:
    async with plant(tmp_path) as gateway, browser() as chromium:
        page = await chromium.new_page(viewport=PHONE)
        await page.goto(f"{gateway.url}#/care")
        chlorine = NAMES[CHLORINE]
        link = page.locator(f"#care section[data-device='{chlorine}'] a[data-calibrate]")
        await link.wait_for()
        documents = await page.evaluate("fetch('/api/care').then((r) => r.json())")
        assert {d["device"] for d in documents} == set(NAMES.values())
        await link.click()
        await page.locator("#calibration-form").wait_for()
        assert page.url.endswith(f"#/calibrate/{chlorine}/slope")
        heading = await page.locator("h1").inner_text()
        assert heading == f"Slope (tecLine/Reiss): {chlorine}"
