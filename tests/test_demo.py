"""``gateway demo`` as a newcomer runs it: values on MQTT and /metrics within seconds, Ctrl-C."""

from __future__ import annotations

import asyncio
import json
import signal
import sys
import urllib.request

import aiomqtt

from tests.mqtt_broker import free_port


async def test_demo_publishes_to_mqtt_and_metrics_then_stops_on_ctrl_c() -> None:
    mqtt_port, metrics_port = free_port(), free_port()
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "gateway",
        "demo",
        "--mqtt-port",
        str(mqtt_port),
        "--metrics-port",
        str(metrics_port),
        "--no-live",
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        assert process.stdout is not None
        banner = ""
        while "Ctrl-C" not in banner:
            banner += (await asyncio.wait_for(process.stdout.readline(), timeout=30)).decode()
        assert f"embedded broker on 127.0.0.1:{mqtt_port}" in banner
        assert f"mosquitto_sub -h 127.0.0.1 -p {mqtt_port} -t 'demo/#' -v" in banner
        received: dict[str, str] = {}
        async with aiomqtt.Client("127.0.0.1", mqtt_port) as client:
            await client.subscribe("demo/#", qos=1)

            async def collect() -> None:
                async for message in client.messages:
                    payload = message.payload
                    received[str(message.topic)] = (
                        payload.decode() if isinstance(payload, bytes) else str(payload)
                    )
                    if {
                        "demo/aeration_oxygen/temperature",
                        "demo/basin_chlorine/concentration",
                    } <= set(received):
                        return

            await asyncio.wait_for(collect(), timeout=15)
            # The write the banner shows goes through, and its result comes back.
            topic = "demo/digester_oxygen/compensation_pressure/set"
            assert f"-t {topic} -m 1003.5" in banner
            await client.subscribe(f"{topic}/result", qos=1)
            await client.publish(topic, "1003.5", qos=1)

            async def result() -> dict[str, object]:
                async for message in client.messages:
                    if str(message.topic) == f"{topic}/result":
                        return json.loads(message.payload)  # type: ignore[no-any-return]
                raise AssertionError("no result")

            outcome = await asyncio.wait_for(result(), timeout=15)
            assert (outcome["status"], outcome["value"]) == ("ok", 1003.5)
        assert float(received["demo/aeration_oxygen/temperature"]) > 0
        url = f"http://127.0.0.1:{metrics_port}/metrics"
        metrics = (
            await asyncio.to_thread(lambda: urllib.request.urlopen(url, timeout=5).read())
        ).decode()
        assert 'gateway_temperature_celsius{bus="demo",device="aeration_oxygen"' in metrics
        assert 'gateway_value_fault{bus="demo",device="fermenter_oxygen"' in metrics
        # The demo's feed keeps the S10's compensation temperature from the tecLine's.
        feed = 'gateway_feed_writes_total{feed="aeration_oxygen/compensation_temperature"'
        assert feed in metrics
        assert (
            'gateway_writes_total{device="digester_oxygen",kind="set",outcome="ok"} 1.0' in metrics
        )
    finally:
        process.send_signal(signal.SIGINT)
        _, err = await asyncio.wait_for(process.communicate(), timeout=15)
    assert process.returncode == 0, err.decode()
