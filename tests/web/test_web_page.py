"""The page in a real browser (headless Debian chromium) against the gateway on the simulator."""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any

import pytest

from tests.web_rig import (
    CHLORINE,
    DESKTOP,
    DIGESTER,
    NAMES,
    OXYGEN,
    PASSWORD,
    PHONE,
    browser,
    plant,
    sign_in,
)

if TYPE_CHECKING:
    from collections.abc import Callable
    from pathlib import Path

    from playwright.async_api import Page

pytestmark = [pytest.mark.line, pytest.mark.browser, pytest.mark.timeout(180)]

CELL_CURRENT_NA = 76.5  # with 0.5 ppm and X_Zero 0: 153 nA/ppm (tecLine 2.4.3's example)
REFERENCE_PPM = 0.5


@pytest.fixture
def screenshots(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Where the screenshots go: beside the tests' temporary files, never in git."""
    path = tmp_path_factory.getbasetemp() / "web-screenshots"
    path.mkdir(exist_ok=True)
    return path


async def _until(
    page: Page, path: str, test: Callable[[Any], object], *, timeout_s: float = 30
) -> Any:
    """GET ``path`` from the page until ``test`` holds of its JSON; that JSON."""
    async with asyncio.timeout(timeout_s):
        while True:
            data = await page.evaluate("path => fetch(path).then(r => r.json())", path)
            if test(data):
                return data
            await asyncio.sleep(0.1)


async def _value(page: Page, device: str, point: str) -> str:
    cell = page.locator(f"section[data-device='{device}'] td[data-value='{point}']")
    return (await cell.inner_text()).strip()


async def test_the_live_table_shows_the_simulators_values_and_a_fault(
    tmp_path: Path, screenshots: Path
) -> None:
    async with plant(tmp_path, absent=True) as gateway, browser() as chromium:
        simulated = gateway.device(CHLORINE).get("temperature")
        page = await chromium.new_page(viewport=PHONE)
        await page.goto(gateway.url)
        chlorine, oxygen = NAMES[CHLORINE], NAMES[OXYGEN]
        temperature = page.locator(
            f"section[data-device='{chlorine}'] td[data-value='temperature']"
        )
        await temperature.wait_for()
        await page.wait_for_function(
            "() => document.querySelector(\"section[data-device='fermenter_oxygen'] "
            "tr[data-point='oxygen']\")"
        )
        assert simulated == 21.5
        assert await _value(page, chlorine, "temperature") == "21.5"
        row = page.locator(f"section[data-device='{oxygen}'] tr[data-point='oxygen']")
        assert "overrange" in await row.inner_text()
        assert await row.get_attribute("class") == "q-fault"
        assert await _value(page, oxygen, "temperature") == "18.25"
        card = page.locator(f"section[data-device='{chlorine}']")
        assert "online" in await card.inner_text()
        # A sensor that does not answer: offline, its timeouts counted by kind.
        missing = page.locator("section[data-device='missing_oxygen']")
        await missing.locator(".badge.offline").wait_for(timeout=15_000)
        assert "errors: timeout" in await missing.inner_text()
        # Live: a new value of the sensor reaches the open page by the event stream.
        gateway.device(CHLORINE).hold("temperature", 23.75)
        await temperature.filter(has_text="23.75").wait_for(timeout=10_000)
        # The page is served from the gateway's own loop, as a named task.
        assert "web" in {task.get_name() for task in asyncio.all_tasks()}
        # No wider than the phone: nothing scrolls sideways.
        width = await page.evaluate("document.documentElement.scrollWidth")
        assert width <= PHONE["width"]
        await page.screenshot(path=screenshots / "live-360.png", full_page=True)
        await page.set_viewport_size(DESKTOP)
        await page.screenshot(path=screenshots / "live-1280.png", full_page=True)
        # Dark, as the phone asks for it.
        dark = await chromium.new_page(viewport=PHONE, color_scheme="dark")
        await dark.goto(gateway.url)
        await dark.locator(f"section[data-device='{chlorine}']").wait_for()
        background = await dark.evaluate("getComputedStyle(document.body).backgroundColor")
        assert background == "rgb(13, 17, 23)"
        await dark.screenshot(path=screenshots / "live-dark-360.png", full_page=True)
        await page.goto(f"{gateway.url}#/health")
        await page.locator("section[data-line='basin']").wait_for()
        assert "Requests" in await page.locator("#health").inner_text()
        await page.screenshot(path=screenshots / "health-1280.png", full_page=True)
        await page.goto(f"{gateway.url}#/device/{chlorine}")
        await page.locator("#register-map tr[data-point='x_span']").wait_for()
        assert "Slope (tecLine/Reiss)" in await page.locator("#procedures").inner_text()
        await page.screenshot(path=screenshots / "device-1280.png", full_page=True)
        await page.set_viewport_size(PHONE)
        await page.screenshot(path=screenshots / "device-360.png", full_page=True)
    assert {"live-360.png", "device-360.png"} <= {p.name for p in screenshots.iterdir()}  # noqa: ASYNC240 - after the loop's work


async def _post(page: Page, path: str, body: object, csrf: str | None) -> dict[str, Any]:
    """A write as the page's own script sends it, with the CSRF token given (or none)."""
    result = await page.evaluate(
        """async ([path, body, csrf]) => {
            const headers = {"Content-Type": "application/json"};
            if (csrf !== null) headers["X-CSRF-Token"] = csrf;
            const r = await fetch(path, {method: "POST", headers, body: JSON.stringify(body)});
            return {status: r.status, body: await r.json()};
        }""",
        [path, body, csrf],
    )
    assert isinstance(result, dict)
    return result


async def test_a_write_without_a_session_or_with_a_bad_csrf_token_is_refused(
    tmp_path: Path,
) -> None:
    async with plant(tmp_path) as gateway, browser() as chromium:
        page = await chromium.new_page()
        await page.goto(gateway.url)
        path = f"/api/devices/{NAMES[CHLORINE]}/points/x_zero"
        refused = await _post(page, path, {"value": "1.0"}, None)
        assert refused["status"] == 401
        calibration = {"device": NAMES[CHLORINE], "procedure": "nominal", "inputs": {}}
        assert (await _post(page, "/api/calibrations", calibration, None))["status"] == 401
        await sign_in(page, gateway.url)
        assert (await _post(page, path, {"value": "1.0"}, "forged"))["status"] == 403
        assert (await _post(page, path, {"value": "1.0"}, None))["status"] == 403
        assert (await _post(page, "/api/calibrations", calibration, "forged"))["status"] == 403
        assert gateway.writes(CHLORINE) == []  # nothing reached the sensor
        # A wrong password opens no session.
        await page.goto(f"{gateway.url}#/login")
        await page.evaluate("fetch('/api/logout', {method: 'POST'})")
        status = await page.evaluate(
            """async () => (await fetch("/api/login", {method: "POST",
                headers: {"Content-Type": "application/json"},
                body: JSON.stringify({name: "eve", password: "guess"})})).status"""
        )
        assert status == 403


async def test_a_write_from_the_register_map_reaches_the_sensor(tmp_path: Path) -> None:
    async with plant(tmp_path) as gateway, browser() as chromium:
        page = await chromium.new_page()
        await sign_in(page, gateway.url)
        await page.goto(f"{gateway.url}#/device/{NAMES[OXYGEN]}")
        form = page.locator("form[data-write='compensation_pressure']")
        await page.click("#read-all")
        await page.locator("#read-all + [role=status]").filter(has_text="values read").wait_for()
        serial = page.locator("#register-map td[data-value='serial_number']")
        assert (await serial.inner_text()).strip() == str(
            gateway.device(OXYGEN).get("serial_number")
        )
        await form.locator("input").fill("1003.5")
        await form.locator("button").click()
        status = form.locator("[role=status]")
        await status.filter(has_text="holds").wait_for()
        assert "1003.5" in await status.inner_text()
        assert gateway.device(OXYGEN).get("compensation_pressure") == 1003.5


async def _start(
    page: Page,
    url: str,
    procedure: str,
    inputs: dict[str, str],
    *,
    address: int = CHLORINE,
    watch: tuple[str, str] = ("cell_current", "nA"),
) -> None:
    """Open a calibration, wait for the live reading, fill the form and start."""
    await page.goto(f"{url}#/calibrate/{NAMES[address]}/{procedure}")
    point, unit = watch
    await page.locator(f"#settle [data-watch='{point}'] .big").filter(has_text=unit).wait_for()
    for name, value in inputs.items():
        if await page.locator(f"select#f-{name}").count():
            await page.select_option(f"#f-{name}", value)
        else:
            await page.fill(f"#f-{name}", value)
    await page.fill("#sign-password", PASSWORD)  # the start is signed
    await page.click("#start")


async def test_a_slope_calibration_runs_from_the_page_and_the_new_slope_is_read_back(
    tmp_path: Path, screenshots: Path
) -> None:
    async with plant(tmp_path) as gateway, browser() as chromium:
        sensor = gateway.device(CHLORINE)
        sensor.hold("cell_current", CELL_CURRENT_NA)
        page = await chromium.new_page(viewport=PHONE)
        await sign_in(page, gateway.url)
        await _start(
            page, gateway.url, "slope", {"reference": "0.5", "samples": "2", "every": "0.2"}
        )
        question = page.locator("#question")
        await question.wait_for(timeout=30_000)
        # The question in plain words first; the registers folded away beneath it.
        summary = await page.locator("#summary").inner_text()
        assert summary.startswith("New slope 153 nA/ppm (was 22 nA/ppm); zero point 0 nA")
        assert "written to the sensor's memory (flash write 1 of 4 allowed today)" in summary
        assert "0x" not in summary
        detail = page.locator("#question-detail pre")
        assert not await detail.is_visible()
        await page.click("#question-detail summary")
        assert "Write 3 register block(s)" in await detail.inner_text()
        assert "x_span = 153" in await detail.inner_text()  # the planned write, before it
        assert not await page.locator("#steps").is_visible()  # every step, folded too
        assert gateway.writes(CHLORINE) == []  # nothing written before the confirmation
        await page.screenshot(path=screenshots / "calibrate-confirm-360.png", full_page=True)
        await page.focus("#confirm-write")
        await page.keyboard.press("Enter")
        await page.locator("#phase[data-phase='done']").wait_for(timeout=30_000)
        result = await page.locator("#result").inner_text()
        assert "calibrated" in result
        verdict = await page.locator("#verdict").inner_text()
        assert verdict == "Calibrated: 3 write(s), every check as expected."
        assert len(result.splitlines()) < 20  # a verdict, not the JSON of every value
        await page.set_viewport_size(DESKTOP)
        await page.screenshot(path=screenshots / "calibrate-done-1280.png", full_page=True)
    assert sensor.get("x_span") == pytest.approx(153.0)
    assert sensor.get("x_zero") == 0.0
    assert [w.address for w in sensor.write_log] == [0x0206, 0x0208, 0x020A]


async def test_not_writing_at_the_confirmation_leaves_the_sensor_as_it_was(
    tmp_path: Path,
) -> None:
    async with plant(tmp_path) as gateway, browser() as chromium:
        sensor = gateway.device(CHLORINE)
        sensor.hold("cell_current", CELL_CURRENT_NA)
        before = sensor.get("x_span")
        page = await chromium.new_page()
        await sign_in(page, gateway.url)
        await _start(page, gateway.url, "slope", {"reference": "0.5", "samples": "1"})
        await page.locator("#question").wait_for(timeout=30_000)
        # One way to say no at the question: "Do not write" (no second "Cancel" beside it).
        assert await page.locator("#question button").count() == 2
        assert await page.locator("#cancel").count() == 0
        await page.click("#decline")
        await page.locator("#phase[data-phase='done']").wait_for(timeout=10_000)
        assert "nothing was written" in await page.locator("#verdict").inner_text()
    assert sensor.write_log == []
    assert sensor.get("x_span") == before


async def test_cancelling_while_the_cell_current_is_read_stops_before_any_write(
    tmp_path: Path,
) -> None:
    async with plant(tmp_path) as gateway, browser() as chromium:
        sensor = gateway.device(CHLORINE)
        sensor.hold("cell_current", CELL_CURRENT_NA)
        page = await chromium.new_page()
        await sign_in(page, gateway.url)
        inputs = {"reference": "0.5", "samples": "20", "every": "0.5"}
        await _start(page, gateway.url, "slope", inputs)
        await page.locator("#progress", has_text="cell_current sample").wait_for()
        await page.focus("#cancel")
        await page.keyboard.press("Enter")
        await page.locator("#phase[data-phase='cancelled']").wait_for(timeout=10_000)
        steps = await page.locator("#steps").inner_text()
        assert "sample 20/20" not in steps
        assert "cancelled by the operator" in await page.locator("#result").inner_text()
        assert await page.locator("#question").count() == 0
    assert sensor.write_log == []


async def test_the_calibration_api_reports_the_steps_as_json(tmp_path: Path) -> None:
    async with plant(tmp_path) as gateway, browser() as chromium:
        page = await chromium.new_page()
        await sign_in(page, gateway.url)
        csrf = await page.evaluate("fetch('/api/session').then(r => r.json()).then(s => s.csrf)")
        body = {
            "device": NAMES[CHLORINE],
            "procedure": "slope",
            "inputs": {"reference": "x"},
            "password": PASSWORD,
        }
        started = await _post(page, "/api/calibrations", body, csrf)
        assert started["status"] == 201
        run_id = started["body"]["id"]
        run = await _until(page, f"/api/calibrations/{run_id}", lambda r: r["phase"] != "running")
        assert run["phase"] == "refused"
        assert "is not a number" in run["error"]
    assert gateway.writes(CHLORINE) == []


# A scan's probe waits a sensor's answer time and no more (at 9600 baud some 50 ms): the
# simulator in this process, starved of CPU beside the rest of the suite, once answered
# address 20 later than that. Alone, with the line's timing as the manuals have it.
@pytest.mark.timing
async def test_a_scan_from_the_page_pauses_the_lines_polling_and_finds_its_sensors(
    tmp_path: Path, screenshots: Path
) -> None:
    async with plant(tmp_path) as gateway, browser() as chromium:
        page = await chromium.new_page(viewport=PHONE)
        await sign_in(page, gateway.url)
        await page.goto(f"{gateway.url}#/scan")
        assert "polling stops" in await page.locator("p.warning").first.inner_text()
        await page.locator("#scan-bus option[value='basin']").wait_for(state="attached")
        await page.fill("#scan-addresses", "1-12,20")
        await page.click("#scan-start")
        state = await _until(page, "/api/state", lambda s: s["lines"][0]["paused"])
        assert "scanned from the web page by ana" in state["lines"][0]["paused"]
        frames_paused = len(gateway.server.bus.frame_log)
        await page.locator("#scan-progress", has_text="Done").wait_for(timeout=60_000)
        await page.screenshot(path=screenshots / "scan-360.png", full_page=True)
        found = page.locator("#scan-found tr")
        assert sorted(
            [
                int(a or 0)
                for a in await found.evaluate_all("rows => rows.map(r => r.dataset.address)")
            ]
        ) == sorted(NAMES)
        assert "jumo-tecline-cl2" in await page.locator("#scan-found").inner_text()
        await _until(page, "/api/state", lambda s: s["lines"][0]["paused"] is None)
    # The scan's probes went out while paused; polling went on after it.
    assert len(gateway.server.bus.frame_log) > frames_paused


@pytest.mark.parametrize(
    ("address", "procedure", "held", "inputs", "watch", "point", "expected"),
    [
        (
            CHLORINE,
            "zero",
            {"cell_current": 0.168},
            {"samples": "1"},
            ("cell_current", "nA"),
            "x_zero",
            0.168,
        ),
        (CHLORINE, "nominal", {}, {}, ("concentration", "ppm"), "x_span", 22.0),
        (
            DIGESTER,
            "oxygen_zero",
            {"phase_shift": 41.25},
            {"mode": "wet"},
            ("temperature", "°C"),
            "zero_point_phase",
            41.25,
        ),
        (
            DIGESTER,
            "oxygen_end_value",
            {"phase_shift": 20.5},
            {"reference": "20.25", "unit": "percent_volume"},
            ("temperature", "°C"),
            "end_value_oxygen",
            20.25,
        ),
    ],
    ids=["tecline-zero", "tecline-nominal", "h10-zero", "h10-end-value"],
)
async def test_every_calibration_runs_from_the_page(
    tmp_path: Path,
    *,
    address: int,
    procedure: str,
    held: dict[str, float],
    inputs: dict[str, str],
    watch: tuple[str, str],
    point: str,
    expected: float,
) -> None:
    async with plant(tmp_path) as gateway, browser() as chromium:
        sensor = gateway.device(address)
        if procedure == "nominal":
            sensor.put("x_span", 30.0)  # a calibrated slope, to go back from
        for name, value in held.items():
            sensor.hold(name, value)
        page = await chromium.new_page()
        await sign_in(page, gateway.url)
        await _start(page, gateway.url, procedure, inputs, address=address, watch=watch)
        await page.locator("#question").wait_for(timeout=30_000)
        assert gateway.writes(address) == []
        summary = await page.locator("#summary").inner_text()
        assert summary.startswith("New ")
        assert "0x" not in summary
        assert "register" not in summary
        await page.click("#confirm-write")
        await page.locator("#phase[data-phase='done']").wait_for(timeout=30_000)
        assert "calibrated" in await page.locator("#result h2").inner_text()
    assert sensor.get(point) == pytest.approx(expected)
    assert gateway.writes(address) != []
