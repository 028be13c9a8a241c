"""The page says which server of ``mqtt.servers`` is in use and how often the gateway moved.

Real parts: two mosquittos, the first stopped while the page is open; headless chromium.
"""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING

import pytest

from tests.mqtt_broker import Broker
from tests.web_rig import DESKTOP, browser, plant, sign_in

if TYPE_CHECKING:
    from pathlib import Path

pytestmark = [pytest.mark.line, pytest.mark.broker, pytest.mark.browser, pytest.mark.timeout(120)]


async def test_the_health_view_names_the_server_in_use_and_counts_the_switches(
    tmp_path: Path,
) -> None:
    first, second = Broker(tmp_path / "first"), Broker(tmp_path / "second")
    for broker in (first, second):
        broker.directory.mkdir()
    servers = f"{{host: 127.0.0.1, port: {first.port}}}, {{host: 127.0.0.1, port: {second.port}}}"
    mqtt = f"{{servers: [{servers}], base_topic: cab7, reconnect_max_s: 1}}"
    with contextlib.ExitStack() as brokers:
        for broker in (first, second):
            broker.start()
            brokers.callback(broker.stop)
        async with plant(tmp_path, mqtt=mqtt) as gateway, browser() as chromium:
            page = await chromium.new_page(viewport=DESKTOP)
            await sign_in(page, gateway.url)
            await page.goto(f"{gateway.url}#/health")
            line = page.locator("p[data-broker='mqtt']")
            await line.filter(
                has_text=f"MQTT: connected to 127.0.0.1:{first.port} (1 of 2) · 0 switches"
            ).wait_for(timeout=20_000)
            first.stop()  # the gateway moves on to the second server
            await line.filter(
                has_text=f"MQTT: connected to 127.0.0.1:{second.port} (2 of 2) · 1 switch"
            ).wait_for(timeout=20_000)
            assert gateway.state.mqtt.switches == 1
            assert await page.locator("p[data-broker='sparkplug']").count() == 0
