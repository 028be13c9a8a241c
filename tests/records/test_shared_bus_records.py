"""Another master's write through the shared bus, recorded with its address and unit.

The gateway polls simulated sensors on a pseudo-terminal and serves a pymodbus client
over Modbus TCP on a real socket (the rig of tests/control/shared_bus). A granted write is
recorded before it reaches the line, with the client's address, its configured name and
the unit, the registers as sent and the points they touch; its outcome after. A write
that is refused never reaches the line, and leaves no record.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import pytest
from pymodbus.client import AsyncModbusTcpClient

from gateway.records import RecordStore, records_path
from tests.control.shared_bus.test_shared_bus import H10, SHARED, TECLINE, plant

if TYPE_CHECKING:
    from pathlib import Path

pytestmark = [pytest.mark.line]


async def test_another_masters_write_is_recorded_with_its_address(tmp_path: Path) -> None:
    async with plant(tmp_path, SHARED) as p:
        client = AsyncModbusTcpClient("127.0.0.1", port=p.tcp_port, timeout=3)
        await client.connect()
        # compensation_temperature of the H10 (0x2013, float CDAB, volatile): 12.5 °C.
        written = await client.write_registers(0x2013, [0x0000, 0x4148], device_id=H10)
        refused = await client.write_register(0x2013, 1, device_id=TECLINE)  # not granted
        client.close()
        log = [w.values for w in p.device(H10).write_log if w.address == 0x2013]
    assert not written.isError()
    assert refused.isError()
    assert log == [(0x0000, 0x4148)]
    store = RecordStore(records_path(tmp_path / "state"), read_only=True)
    records = [r for r in store.records() if r.kind in {"write", "outcome"}]
    write, outcome = records  # the refused one left none
    actor = write.body["actor"]
    assert (actor["user"], actor["via"]) == ("127.0.0.1", "shared-bus")
    assert actor["detail"].startswith("client ")
    assert actor["detail"].endswith(f"unit {H10}")
    assert "connection 127.0.0.1:" in actor["detail"]
    assert write.body["device"]["name"] == "oxygen"
    assert write.body["device"]["address"] == H10
    assert [p["point"] for p in write.body["points"]] == ["compensation_temperature"]
    assert write.body["data"] == {
        "function": 16,
        "address": "0x2013",
        "registers": ["0x0000", "0x4148"],
    }
    assert outcome.body["completes"] == write.seq
    assert outcome.body["result"] == "done"
    assert store.verify().intact
