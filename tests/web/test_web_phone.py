"""The page on a phone at the basin: 360 px wide, in headless chromium, on the simulator.

Values drawn on one line and controls inside the screen are measured in the browser (the
client rectangles of each value's text, the bounding box of each control), not guessed from
the CSS; calibrations left at their question, taken over, or answered from another session
run against the simulator, whose write log shows what reached the sensor.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from typing import TYPE_CHECKING, Any

import pytest

from tests.web_rig import (
    CHLORINE,
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
    from pathlib import Path

    from playwright.async_api import Page

pytestmark = [pytest.mark.line, pytest.mark.browser, pytest.mark.timeout(180)]

CELL_CURRENT_NA = 76.5  # with 0.5 ppm and X_Zero 0: 153 nA/ppm (tecLine 2.4.3's example)

# Every number, date and word of the register map's values drawn on one line (an inline box
# broken over two lines has client rectangles at two heights: text may wrap between its words,
# never inside one), and every value and control inside the viewport's width.
_MEASURE = """() => {
  const width = document.documentElement.clientWidth;
  const broken = [], outside = [];
  for (const v of document.querySelectorAll("#identity .nowrap, #register-map td[data-value] .nowrap")) {
    if (!v.textContent) continue;
    const rects = [...v.getClientRects()].filter((r) => r.width > 0);
    const lines = new Set(rects.map((r) => Math.round(r.top)));
    if (lines.size > 1) broken.push(v.textContent);
    for (const r of rects) if (r.left < 0 || r.right > width) outside.push(v.textContent);
  }
  const controls = document.querySelectorAll("main button, main input, main select, main summary");
  let drawn = 0;
  for (const c of controls) {
    const r = c.getBoundingClientRect();
    if (r.width === 0 && r.height === 0) continue;  // not drawn (a closed fold's content)
    drawn += 1;
    if (r.left < 0 || r.right > width) outside.push(c.outerHTML.slice(0, 80));
  }
  for (const e of document.querySelectorAll("body *")) { const r = e.getBoundingClientRect(); if (r.right > width + 1) outside.push("wide: " + e.tagName + "." + e.className + " " + (e.textContent || "").slice(0, 40)); }
  return {broken, outside, drawn, values: document.querySelectorAll("#register-map .v").length,
          scroll: document.documentElement.scrollWidth, width};
}"""


@pytest.fixture
def screenshots(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Where the screenshots go: beside the tests' temporary files, never in git."""
    path = tmp_path_factory.getbasetemp() / "web-screenshots"
    path.mkdir(exist_ok=True)
    return path


async def _measure(page: Page) -> dict[str, Any]:
    result = await page.evaluate(_MEASURE)
    assert isinstance(result, dict)
    return result


@pytest.mark.parametrize("address", [CHLORINE, OXYGEN, DIGESTER], ids=["tecline", "h20", "h10"])
async def test_on_a_phone_every_value_is_one_line_and_every_control_on_screen(
    tmp_path: Path, screenshots: Path, address: int
) -> None:
    async with plant(tmp_path) as gateway, browser() as chromium:
        page = await chromium.new_page(viewport=PHONE)
        await sign_in(page, gateway.url)
        await page.goto(f"{gateway.url}#/device/{NAMES[address]}")
        await page.locator("#register-map tr[data-point]").first.wait_for()
        await page.click("#read-all")  # every register, dates and serial numbers too
        await page.locator("#read-all + [role=status]").filter(has_text="values read").wait_for()
        measured = await _measure(page)
        assert measured["values"] > 20
        assert measured["drawn"] >= 1  # the read button, and the write forms where offered
        assert measured["broken"] == []
        assert measured["outside"] == []
        assert measured["scroll"] <= PHONE["width"]
        if address == OXYGEN:  # a RAM point: its form, on the screen
            button = page.locator("form[data-write='compensation_pressure'] button")
            box = await button.bounding_box()
            assert box is not None
            assert box["x"] >= 0
            assert box["x"] + box["width"] <= PHONE["width"]
        if address == CHLORINE:  # a flash point not in flash_writes: why, and no form
            refused = page.locator("tr[data-write-row='x_span']")
            assert "Not writable: flash, not in flash_writes" in await refused.inner_text()
            assert await page.locator("form[data-write='x_span']").count() == 0
        await page.screenshot(path=screenshots / f"device-{address}-360.png", full_page=True)


async def _question(page: Page, url: str) -> None:
    """Start a slope calibration of the tecLine and wait for its question."""
    await page.goto(f"{url}#/calibrate/{NAMES[CHLORINE]}/slope")
    await page.locator("#settle [data-watch='cell_current'] .big").filter(has_text="nA").wait_for()
    await page.fill("#f-reference", "0.5")
    await page.fill("#f-samples", "1")
    await page.fill("#sign-password", PASSWORD)  # the start is signed
    await page.click("#start")
    await page.locator("#question").wait_for(timeout=30_000)


async def _api(page: Page, method: str, path: str) -> dict[str, Any]:
    """A request as the page's script makes it, with its session's CSRF token."""
    result = await page.evaluate(
        """async ([method, path]) => {
            const s = await (await fetch("/api/session")).json();
            const headers = {"Content-Type": "application/json"};
            if (s.csrf) headers["X-CSRF-Token"] = s.csrf;
            const body = method === "POST" ? JSON.stringify({confirm: true}) : undefined;
            const r = await fetch(path, {method, headers, body});
            return {status: r.status, body: await r.json()};
        }""",
        [method, path],
    )
    assert isinstance(result, dict)
    return result


async def _ended(page: Page, run_id: str, timeout_s: float = 15) -> dict[str, Any]:
    """The run once it has ended (as the page reads it).

    A question left unanswered sends the run back to ``running`` while the flow unwinds
    (and its record is written): the end is the phase after that.
    """
    async with asyncio.timeout(timeout_s):
        while True:
            run = (await _api(page, "GET", f"/api/calibrations/{run_id}"))["body"]
            assert isinstance(run, dict)
            if run["phase"] not in {"confirm", "running", "writing"}:
                return run
            await asyncio.sleep(0.2)


# Sessions and questions that expire in seconds, on the clock: alone, or a loaded machine's
# new browser context takes the seconds between the session's end and the question's.
@pytest.mark.timing
async def test_a_calibration_left_at_its_question_ends_and_frees_the_device(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # Sessions end 3 s after their last write, questions 6 s after they are asked.
    web = ", session_minutes: 0.05, confirm_minutes: 0.1"
    async with plant(tmp_path, web=web) as gateway, browser() as chromium:
        sensor = gateway.device(CHLORINE)
        sensor.hold("cell_current", CELL_CURRENT_NA)
        phone = await chromium.new_context(viewport=PHONE)
        page = await phone.new_page()
        await sign_in(page, gateway.url)
        await _question(page, gateway.url)
        cookies = await phone.cookies()
        await phone.close()  # the phone locked at the basin: nobody answers
        # While its calibration is under way, the session outlives session_minutes.
        await asyncio.sleep(4)
        later = await chromium.new_context()
        await later.add_cookies(cookies)  # type: ignore[arg-type]
        same = await later.new_page()
        await same.goto(gateway.url)
        session = await same.evaluate("fetch('/api/session').then(r => r.json())")
        assert session["signed_in"] is True
        runs = await same.evaluate(
            f"fetch('/api/calibrations?device={NAMES[CHLORINE]}').then(r => r.json())"
        )
        assert [r["phase"] for r in runs["runs"]] == ["confirm"]
        run_id = runs["runs"][0]["id"]
        # The question ends by itself, nothing written; then the session goes too.
        run = await _ended(same, run_id)
        assert run["phase"] == "abandoned"
        assert run["verdict"] == "Ended: no answer in time. Nothing was written."
        await asyncio.sleep(3.5)
        session = await same.evaluate("fetch('/api/session').then(r => r.json())")
        assert session["signed_in"] is False
        # The device is free: another operator sees nothing under way and calibrates.
        other = await chromium.new_page(viewport=PHONE)
        await sign_in(other, gateway.url, name="ben")
        await other.goto(f"{gateway.url}#/device/{NAMES[CHLORINE]}")
        await other.locator("#procedures").wait_for()
        assert await other.locator("#under-way [data-run]").count() == 0
        await _question(other, gateway.url)
    assert sensor.write_log == []
    assert "ended: no answer in time; nothing was written" in caplog.text


@pytest.mark.parametrize("action", ["take-over", "cancel"])
async def test_another_session_cannot_answer_but_can_take_over_or_cancel(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, action: str
) -> None:
    caplog.set_level(logging.INFO, logger="gateway.web")
    async with plant(tmp_path) as gateway, browser() as chromium:
        sensor = gateway.device(CHLORINE)
        sensor.hold("cell_current", CELL_CURRENT_NA)
        ana = await (await chromium.new_context(viewport=PHONE)).new_page()
        await sign_in(ana, gateway.url)
        await _question(ana, gateway.url)
        run_id = (await _api(ana, "GET", f"/api/calibrations?device={NAMES[CHLORINE]}"))["body"][
            "runs"
        ][0]["id"]
        ben = await (await chromium.new_context(viewport=PHONE)).new_page()
        await sign_in(ben, gateway.url, name="ben")
        # A confirmation is bound to the session that started the run.
        refused = await _api(ben, "POST", f"/api/calibrations/{run_id}/answer")
        assert refused["status"] == 403
        assert "take it over" in refused["body"]["error"]
        assert sensor.write_log == []
        # The device's page shows the run to any signed-in user, with what can be done.
        await ben.goto(f"{gateway.url}#/device/{NAMES[CHLORINE]}")
        banner = ben.locator(f"#under-way [data-run='{run_id}']")
        await banner.wait_for()
        assert "started by ana@127.0.0.1 is waiting for its confirmation" in (
            await banner.inner_text()
        )
        if action == "cancel":
            await ben.click("#cancel-other")
            await banner.locator("[role=status]", has_text="cancelled").wait_for()
            assert "ben@127.0.0.1 cancelled the slope calibration" in caplog.text
            assert sensor.write_log == []
            return
        await ben.click("#take-over")
        await ben.locator("#question #summary").wait_for()  # now ben's question
        assert "ben@127.0.0.1 took over the slope calibration of pool_chlorine" in caplog.text
        # ana's page no longer offers the writes, and her answer is refused.
        await ana.locator(".warning", has_text="ben@127.0.0.1 has taken").wait_for()
        assert (await _api(ana, "POST", f"/api/calibrations/{run_id}/answer"))["status"] == 403
        await ben.click("#confirm-write")
        await ben.locator("#phase[data-phase='done']").wait_for(timeout=30_000)
    assert [w.address for w in sensor.write_log] == [0x0206, 0x0208, 0x020A]


def _own_address() -> str | None:
    """This machine's address on its network (no packet is sent), or ``None``."""
    with contextlib.suppress(OSError), socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.connect(("192.0.2.1", 9))  # TEST-NET-1: only the route is looked up
        address = str(probe.getsockname()[0])
        return None if address.startswith("127.") else address
    return None


async def test_from_another_machine_the_sign_in_page_says_reading_needs_it_too(
    tmp_path: Path,
) -> None:
    address = _own_address()
    if address is None:
        pytest.skip("this machine has no address but loopback")
    async with plant(tmp_path, web=", host: 0.0.0.0") as gateway, browser() as chromium:
        page = await chromium.new_page(viewport=PHONE)
        remote = f"http://{address}:{gateway.port}/"
        await page.goto(remote)
        intro = page.locator("main p").first
        await intro.filter(has_text="reading").wait_for()
        assert "From another machine, reading this page needs you to sign in too" in (
            await intro.inner_text()
        )
        await sign_in(page, remote)
        await page.locator("section[data-device] td[data-value]").first.wait_for()
        # On this machine the page reads without a session, and says only writes need one.
        local = await chromium.new_page(viewport=PHONE)
        await local.goto(f"{gateway.url}#/login")
        assert await local.locator("main p").first.inner_text() == (
            "Writes and calibrations need you to sign in."
        )


async def test_signing_out_at_the_question_ends_the_calibration_unwritten(tmp_path: Path) -> None:
    async with plant(tmp_path) as gateway, browser() as chromium:
        sensor = gateway.device(CHLORINE)
        sensor.hold("cell_current", CELL_CURRENT_NA)
        page = await chromium.new_page(viewport=PHONE)
        await sign_in(page, gateway.url)
        await _question(page, gateway.url)
        run_id = (await _api(page, "GET", f"/api/calibrations?device={NAMES[CHLORINE]}"))["body"][
            "runs"
        ][0]["id"]
        await page.click("#sign-out")
        await page.locator("#sign-in-link").wait_for()
        run = await _ended(page, run_id)
        assert run["phase"] == "abandoned"
        assert run["verdict"] == "Ended: ana signed out. Nothing was written."
    assert sensor.write_log == []
