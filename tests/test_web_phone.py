"""The page on a phone at the basin: 360 px wide, in headless chromium, on the simulator.

Values drawn on one line and controls inside the screen are measured in the browser (the
client rectangles of each value's text, the bounding box of each control), not guessed from
the CSS; calibrations left at their question, taken over, or answered from another session
run against the simulator, whose write log shows what reached the sensor.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any

import pytest

from tests.web_rig import CHLORINE, DIGESTER, NAMES, OXYGEN, PHONE, browser, plant, sign_in

if TYPE_CHECKING:
    from pathlib import Path

    from playwright.async_api import Page

pytestmark = pytest.mark.timeout(180)

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
            assert 0 <= box["x"]
            assert box["x"] + box["width"] <= PHONE["width"]
        if address == CHLORINE:  # a flash point not in flash_writes: why, and no form
            refused = page.locator("tr[data-write-row='x_span']")
            assert "not in this device's flash_writes" in await refused.inner_text()
            assert await page.locator("form[data-write='x_span']").count() == 0
        await page.screenshot(path=screenshots / f"device-{address}-360.png", full_page=True)
