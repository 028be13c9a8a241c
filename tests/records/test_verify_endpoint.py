"""``POST /verify`` on the metrics port, as careless or hostile clients call it.

The metrics server on a real socket, its verification hook a recorder of what reached it:
a body that is not JSON, not an object, empty or too large is answered 400 and never
reaches the gateway; a GET of it is 404; ``/metrics`` answers on after them.
"""

from __future__ import annotations

import http.client
import json
from typing import TYPE_CHECKING

from gateway.publish.prometheus import MetricsServer
from gateway.publish.prometheus.endpoint import MAX_POST_BYTES
from gateway.shared.state import GatewayState

if TYPE_CHECKING:
    from collections.abc import Mapping


def post(port: int, body: bytes) -> tuple[int, dict[str, object]]:
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    try:
        connection.request("POST", "/verify", body=body, headers={"Content-Type": "x"})
        answer = connection.getresponse()
        return answer.status, json.loads(answer.read())
    finally:
        connection.close()


def test_bad_requests_never_reach_the_gateway_and_metrics_go_on() -> None:
    reached: list[Mapping[str, object]] = []
    state = GatewayState()

    def verify(body: Mapping[str, object]) -> tuple[int, dict[str, object]]:
        reached.append(body)
        return 200, {"status": "ok"}

    state.writes.verify = verify
    with MetricsServer(state, host="127.0.0.1", port=0) as server:
        for bad in (b"", b"not json", b"[1, 2]", b"{" * 10, b" " * (MAX_POST_BYTES + 1)):
            status, answer = post(server.port, bad)
            assert status == 400, (bad[:20], answer)
            assert answer["status"] == "refused"
        assert reached == []
        connection = http.client.HTTPConnection("127.0.0.1", server.port, timeout=5)
        connection.request("GET", "/verify")
        assert connection.getresponse().status == 404
        connection.close()
        status, answer = post(server.port, b'{"device": "basin", "reference": 0.5}')
        assert (status, answer) == (200, {"status": "ok"})
        assert reached == [{"device": "basin", "reference": 0.5}]
        metrics = http.client.HTTPConnection("127.0.0.1", server.port, timeout=5)
        metrics.request("GET", "/metrics")
        assert metrics.getresponse().status == 200
        metrics.close()
