"""The records view without a line: the query checked, writes joined to outcomes, a page without a store.

A real record store in a temporary directory, records appended as the write path appends
them (a write, then the outcome that completes it); the page's server started without a
store or a verifier answers with what is missing, not with an error of its own.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

import aiohttp
import pytest

from gateway.config import WebConfig
from gateway.errors import CommandRejectedError
from gateway.records import (
    Actor,
    DeviceRef,
    Entry,
    Kind,
    PointChange,
    RecordStore,
    Result,
    Via,
    records_path,
)
from gateway.shared.state import GatewayState
from gateway.web import WebServer
from gateway.web.records import MAX_LIMIT, RecordsRequest, read_records, value_text
from tests.mqtt_broker import free_port

if TYPE_CHECKING:
    from pathlib import Path

PASSWORD = "s3cret"  # noqa: S105 - the tests' own
ANA = Actor(user="ana", via=Via.PAGE, detail="192.0.2.7", reason="new barometer")
POOL = DeviceRef(name="pool", profile="jumo-tecline-cl2", serial="0104")
TANK = DeviceRef(name="tank", profile="jumo-digiline-odo-h20")


def _store(tmp_path: Path) -> RecordStore:
    """Two devices' writes with their outcomes, and a verification, in a real store."""
    store = RecordStore(records_path(tmp_path), clock_synchronised=lambda: True)
    for device, found, left in ((POOL, 1013.25, 1003.5), (TANK, 7, 8)):
        write = store.append(
            Entry(
                kind=Kind.WRITE,
                actor=ANA,
                device=device,
                action="write compensation_pressure",
                result=Result.PENDING,
                points=(PointChange(point="compensation_pressure", as_found=found, sent=left),),
            )
        )
        store.append(
            Entry(
                kind=Kind.OUTCOME,
                actor=ANA,
                device=device,
                action="write compensation_pressure",
                result=Result.DONE,
                points=(PointChange(point="compensation_pressure", unit="mbar", as_left=left),),
                completes=write.seq,
            )
        )
    store.append(
        Entry(
            kind=Kind.VERIFICATION,
            actor=Actor(user="ana", via=Via.PAGE, signed=True),
            device=POOL,
            action="grab-sample verification (DPD)",
            result=Result.PASSED,
            points=(PointChange(point="concentration", unit="mg/l", as_found=0.48),),
            data={"reference": 0.5},
        )
    )
    return store


def _read(path: Path, **asked: Any) -> dict[str, Any]:
    """The view's JSON, as the page gets it."""
    return dict(read_records(path, RecordsRequest.parse(**asked)))


def test_the_query_string_is_checked_where_it_comes_in() -> None:
    asked = RecordsRequest.parse(
        device="pool", kinds=["write,outcome", "write"], since="2025-06-01", limit="20"
    )
    assert asked.query.kinds == ("outcome", "write")
    assert asked.query.since == datetime(2025, 6, 1, tzinfo=UTC)  # no zone: UTC
    assert asked.limit == 20
    assert RecordsRequest.parse().limit == 500
    for wrong, says in (
        ({"kinds": ["rumour"]}, "no kind of record rumour"),
        ({"since": "last week"}, "not an ISO 8601 time"),
        ({"limit": "all"}, "whole number"),
        ({"limit": str(MAX_LIMIT + 1)}, "gateway records export"),
    ):
        with pytest.raises(CommandRejectedError, match=says):
            RecordsRequest.parse(**wrong)


def test_values_read_as_a_table_cell_does() -> None:
    assert value_text({"code": 2, "label": "mg/l"}) == "mg/l"
    assert value_text({"fault": "overrange", "raw": 2.0e37}) == "fault: overrange"
    assert value_text({"word": 0, "bits": []}) == "no bit set"
    assert value_text(0.1 + 0.2) == "0.3"
    assert value_text(None) == ""


def test_records_newest_first_each_write_with_its_outcome_and_the_chains_verdict(
    tmp_path: Path,
) -> None:
    _store(tmp_path).close()
    path = records_path(tmp_path)
    every = _read(path)
    assert [r["seq"] for r in every["records"]] == [5, 4, 3, 2, 1]
    assert every["verdict"]["intact"] is True
    assert every["head"]["seq"] == 5
    assert every["more"] is False
    write = every["records"][4]
    assert (write["user"], write["via"], write["reason"]) == ("ana", "page", "new barometer")
    assert write["points"][0]["as_found"] == 1013.25
    assert write["points"][0]["as_left"] == 1003.5  # joined from record 2
    assert write["outcome"] == {"seq": 2, "result": "done"}
    outcome = every["records"][3]
    assert outcome["points"][0]["as_found"] == 1013.25  # joined from record 1
    assert every["records"][0]["signed"] is True

    # Only writes of one device: the outcome was not chosen, and is still joined.
    (alone,) = _read(path, device="tank", kinds=["write"])["records"]
    assert alone["seq"] == 3
    assert alone["points"][0]["as_left"] == 8
    newest = _read(path, limit="2")
    assert [r["seq"] for r in newest["records"]] == [5, 4]
    assert newest["more"] is True
    head_only = _read(path, limit="0")
    assert head_only["records"] == []
    assert head_only["head"]["short"] == head_only["head"]["hash"][:12]


async def test_a_page_without_a_store_or_a_verifier_says_so() -> None:
    config = WebConfig.model_validate({"enabled": True, "port": free_port(), "password": PASSWORD})
    server = WebServer(config, GatewayState(), {})
    await server.start()
    try:
        jar = aiohttp.CookieJar(unsafe=True)
        async with aiohttp.ClientSession(cookie_jar=jar) as http:
            url = server.url

            async def call(method: str, path: str, **kwargs: Any) -> tuple[int, dict[str, Any]]:
                async with http.request(method, f"{url}{path}", **kwargs) as response:
                    return response.status, await response.json()

            status, body = await call("GET", "api/records")
            assert status == 404
            assert "no record store" in body["error"]
            status, body = await call("GET", "api/devices/pool/verification")
            assert status == 503
            status, signed = await call(
                "POST", "api/login", json={"name": "ana", "password": PASSWORD}
            )
            assert status == 200
            status, body = await call(
                "POST",
                "api/devices/pool/verify",
                json={"reference": 0.5, "method": "DPD", "password": PASSWORD},
                headers={"X-CSRF-Token": signed["csrf"]},
            )
            assert status == 503
            assert "no verifier" in body["error"]
            status, state = await call("GET", "api/state")
            assert "records" not in state  # no head in the footer
    finally:
        await server.stop()
