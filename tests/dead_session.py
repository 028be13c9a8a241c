"""A converter that vanishes without a word, in a network namespace of its own.

Run as ``unshare -rn python -m tests.dead_session SCHEME busy|idle USER_TIMEOUT_S``: the
simulator serves on the namespace's loopback, a line connects to it, answers once, and then
every packet to the simulator is dropped (iptables, as a pulled cable or a powered-off
converter does it: no FIN, no RST). Prints, as JSON, how long the session lasted after
that and how many requests failed meanwhile. Only ``tests/line/test_tcp_session.py`` runs it.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time

from gateway.config.network import TcpSettings
from gateway.errors import GatewayError
from gateway.line.boundary import RequestOptions
from gateway.line.transports.factory import build_line
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.wire import frames
from gateway.wire.timing import LineFormat

DEVICES = [{"profile": "jumo-digiline-odo-s10", "address": 1}]


async def measure(scheme: str, *, busy: bool, settings: TcpSettings) -> dict[str, object]:
    server = SimulatorServer(build_bus(parse_settings({"devices": DEVICES})))
    framing = "tcp" if scheme == "tcp" else "rtu"
    port = await server.open_tcp("127.0.0.1", 0, framing=framing)
    line = build_line(port=f"{scheme}://127.0.0.1:{port}", line=LineFormat(), tcp=settings)
    request = frames.read_request(1, 0x2620, 2)
    failures = 0
    try:
        await line.open()
        assert await line.transact(request, RequestOptions(timeout_s=0.2, gap_s=0.005)) is not None
        drop = ["-A", "INPUT", "-p", "tcp", "--dport", str(port), "-j", "DROP"]
        iptables = await asyncio.create_subprocess_exec("iptables", *drop)
        assert await iptables.wait() == 0
        dropped = time.monotonic()
        while line.is_open and time.monotonic() - dropped < 30:
            if busy:
                try:
                    await line.transact(request, RequestOptions(timeout_s=0.2, gap_s=0.005))
                except GatewayError:
                    failures += 1
            await asyncio.sleep(0.1)
        return {"ended_after_s": time.monotonic() - dropped, "failures": failures}
    finally:
        await line.close()
        await server.close()


def main() -> None:
    scheme, mode, user_timeout = sys.argv[1], sys.argv[2], float(sys.argv[3])
    settings = TcpSettings(
        keepalive_s=1, keepalive_interval_s=1, user_timeout_s=user_timeout, silent_requests=0
    )
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)  # noqa: S607 - in the namespace
    result = asyncio.run(measure(scheme, busy=mode == "busy", settings=settings))
    sys.stdout.write(json.dumps(result) + "\n")


if __name__ == "__main__":
    main()
