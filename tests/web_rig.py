"""The web page's test rig: the gateway with its page, on a simulated line, and a real browser.

The gateway runs as ``gateway run`` does (:func:`gateway.app.run`, in the test's loop) against
the sensor simulator on a pseudo-terminal; the browser is Debian's headless ``chromium``
driven by playwright (``executable_path``: no browser of playwright's own is downloaded).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import shutil
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from playwright.async_api import async_playwright

from gateway.app import run
from gateway.config import parse_config
from gateway.shared.state import GatewayState
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from tests.mqtt_broker import free_port

if TYPE_CHECKING:
    from collections.abc import AsyncIterator
    from pathlib import Path

    from playwright.async_api import Browser, Page, ViewportSize

    from gateway.simulator.device import SimulatedDevice

PASSWORD = "correct horse battery"  # noqa: S105 - the test gateway's
CHLORINE = 20  # tecLine Cl2
OXYGEN = 3  # H20, its oxygen in fault
DIGESTER = 2  # H10
REISS = 10
PLANT: list[dict[str, Any]] = [
    {
        "profile": "jumo-tecline-cl2",
        "address": CHLORINE,
        "animate": False,
        "values": {"temperature": 21.5},
    },
    {
        "profile": "jumo-digiline-odo-h20",
        "address": OXYGEN,
        "animate": False,
        "values": {"oxygen": {"fault": "overrange"}, "temperature": 18.25},
    },
    {"profile": "jumo-digiline-odo-h10", "address": DIGESTER, "animate": False},
    {"profile": "reiss-m0c", "address": REISS, "animate": False},
]
NAMES = {
    CHLORINE: "pool_chlorine",
    OXYGEN: "fermenter_oxygen",
    DIGESTER: "digester_oxygen",
    REISS: "basin_chlorine",
}
LINE = {"baudrate": 19200, "parity": "E", "stopbits": 1}
PHONE: ViewportSize = {"width": 360, "height": 780}
DESKTOP: ViewportSize = {"width": 1280, "height": 900}


def chromium() -> str:
    """Debian's chromium (``scripts/setup test`` installs it)."""
    path = shutil.which("chromium")
    if path is None:
        msg = "no chromium on PATH: run scripts/setup test (apt-get install chromium)"
        raise RuntimeError(msg)
    return path


@dataclass
class Plant:
    """The simulator, the running gateway and where its page is."""

    server: SimulatorServer
    state: GatewayState
    url: str
    port: int

    def device(self, address: int) -> SimulatedDevice:
        return self.server.bus.devices[address]

    def writes(self, address: int) -> list[Any]:
        return list(self.device(address).write_log)


ABSENT = 7  # configured, but no sensor answers there


def _config(
    tty: Path,
    port: int,
    state_dir: Path,
    *,
    password: str | None,
    absent: bool,
    web: str,
    mqtt: str = "{enabled: false}",
) -> str:
    devices = "".join(
        f"  - {{name: {name}, bus: basin, address: {address}, "
        f"profile: {next(d['profile'] for d in PLANT if d['address'] == address)}, "
        "poll_interval: 0.5}\n"
        for address, name in NAMES.items()
    )
    if absent:
        devices += (
            f"  - {{name: missing_oxygen, bus: basin, address: {ABSENT}, "
            "profile: jumo-digiline-odo-s10, poll_interval: 0.5}\n"
        )
    secret = f", password: {json.dumps(password)}" if password else ""
    return (
        # The bus waits 0.3 s for an answer (the default at 19200 baud is under 0.1 s): the
        # page is under test, not the line, and on a machine running tests side by side the
        # simulator in this process answers late now and then (a write that timed out
        # stopped a calibration on the page).
        f"buses:\n  - {{name: basin, port: {json.dumps(str(tty))}, baudrate: 19200, parity: E,"
        " timeout: 0.3}\n"
        f"devices:\n{devices}"
        f"mqtt: {mqtt}\n"
        "prometheus: {enabled: false}\n"
        f"web: {{enabled: true, port: {port}{secret}{web}}}\n"
        f"state_dir: {json.dumps(str(state_dir))}\n"
    )


@contextlib.asynccontextmanager
async def plant(
    tmp_path: Path,
    *,
    password: str | None = PASSWORD,
    absent: bool = False,
    web: str = "",
    mqtt: str = "{enabled: false}",
) -> AsyncIterator[Plant]:
    """The gateway with its page polling the simulated plant; stopped at the end.

    With ``absent``, one more device is configured where no sensor answers; ``web`` adds
    keys to the ``web`` section (``", confirm_minutes: 0.1"``); ``mqtt`` is the ``mqtt``
    section (off by default).
    """
    server = SimulatorServer(build_bus(parse_settings({"devices": PLANT, "line": LINE})))
    tty = tmp_path / "ttyRS485"
    server.open_pty(tty)
    port = free_port()
    text = _config(
        tty, port, tmp_path / "state", password=password, absent=absent, web=web, mqtt=mqtt
    )
    config = parse_config(text, environ={})
    state = GatewayState()
    stop = asyncio.Event()
    task = asyncio.create_task(run(config, state=state, stop=stop), name="test.gateway")
    try:
        for _ in range(100):  # the page listens once the gateway has started
            with contextlib.suppress(OSError):
                _, writer = await asyncio.open_connection("127.0.0.1", port)
                writer.close()
                await writer.wait_closed()
                break
            if task.done():
                await task
            await asyncio.sleep(0.05)
        yield Plant(server=server, state=state, url=f"http://127.0.0.1:{port}/", port=port)
    finally:
        stop.set()
        await asyncio.wait_for(task, timeout=10)
        await server.close()


@contextlib.asynccontextmanager
async def browser() -> AsyncIterator[Browser]:
    """Headless Debian chromium."""
    async with async_playwright() as driver:
        launched = await driver.chromium.launch(executable_path=chromium(), headless=True)
        try:
            yield launched
        finally:
            await launched.close()


async def sign_in(page: Page, url: str, *, name: str = "ana", password: str = PASSWORD) -> None:
    """Sign in through the page's own form."""
    await page.goto(f"{url}#/login")
    await page.fill("#login-name", name)
    await page.fill("#login-password", password)
    await page.click("#login-submit")
    await page.wait_for_selector("#who-name:has-text('Signed in')")
