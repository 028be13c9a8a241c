"""The records view and the verification form's route on the running page, on the simulator.

The gateway runs with its page against the simulator (``tests/web_rig.plant``), its record
store and users file in its state directory; the requests are the page's own, sent by an
HTTP client with a cookie jar (``tests/web/test_web_users.Client``), and the simulator's
write log says what reached the sensors.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any

import pytest

from gateway.records import RecordStore, records_path
from gateway.records.actor import Via
from gateway.web.users import USERS_FILE, Role, UserBook
from tests.web.test_web_users import (
    OPERATOR,
    OPERATOR_PASSWORD,
    PRESSURE,
    VIEWER,
    VIEWER_PASSWORD,
    Client,
    client,
)
from tests.web_rig import CHLORINE, NAMES, OXYGEN, plant

if TYPE_CHECKING:
    from pathlib import Path

pytestmark = [pytest.mark.line, pytest.mark.timeout(120)]

POOL = NAMES[CHLORINE]
FERMENTER = NAMES[OXYGEN]


def _users(tmp_path: Path) -> None:
    book = UserBook(tmp_path / "state" / USERS_FILE)
    book.add(OPERATOR, Role.OPERATOR, OPERATOR_PASSWORD)
    book.add(VIEWER, Role.VIEWER, VIEWER_PASSWORD)


async def _get(page: Client, path: str) -> tuple[int, dict[str, Any]]:
    async with page.http.get(f"{page.url}{path}") as response:
        data: dict[str, Any] = await response.json()
        return response.status, data


async def _chlorine(page: Client) -> float:
    """The pool sensor's process value, once the gateway has polled it."""
    async with asyncio.timeout(30):
        while True:
            state = await page.get("api/state")
            device = next(d for d in state["devices"] if d["name"] == POOL)
            value = next((v for v in device["values"] if v["point"] == "concentration"), None)
            if value is not None and value["quality"] == "good":
                return float(value["text"])
            await asyncio.sleep(0.1)


async def test_a_write_through_the_page_is_listed_with_its_user_and_values_and_filtered(
    tmp_path: Path,
) -> None:
    _users(tmp_path)
    async with plant(tmp_path) as gateway, client(gateway.url) as page:
        before = gateway.device(OXYGEN).get("compensation_pressure")
        await page.sign_in(OPERATOR, OPERATOR_PASSWORD)
        status, body = await page.post(PRESSURE, {"value": "1003.5", "reason": "new barometer"})
        assert status == 200, body

        listed = await page.get("api/records")
        assert listed["verdict"]["intact"] is True
        head = listed["head"]
        assert head["seq"] == listed["records"][0]["seq"]  # newest first
        assert head["short"] == head["hash"][:12]
        seqs = [r["seq"] for r in listed["records"]]
        assert seqs == sorted(seqs, reverse=True)
        write = next(r for r in listed["records"] if r["kind"] == "write")
        assert (write["user"], write["via"], write["device"]) == (
            OPERATOR,
            str(Via.PAGE),
            FERMENTER,
        )
        assert write["reason"] == "new barometer"
        assert write["action"] == "write compensation_pressure"
        (point,) = write["points"]
        assert point["point"] == "compensation_pressure"
        assert point["as_found"] == pytest.approx(before)
        assert point["as_left"] == 1003.5  # from the outcome record that completes the write
        assert write["outcome"]["result"] == "done"
        outcome = next(r for r in listed["records"] if r["seq"] == write["outcome"]["seq"])
        assert outcome["kind"] == "outcome"
        assert outcome["points"][0]["as_found"] == pytest.approx(before)

        # The filters: by kind, by device, by both; a write alone still shows its as-left.
        only = await page.get("api/records?kind=write")
        assert {r["kind"] for r in only["records"]} == {"write"}
        assert only["records"][0]["points"][0]["as_left"] == 1003.5
        both = await page.get(f"api/records?device={FERMENTER}&kind=write&kind=outcome")
        assert [r["seq"] for r in both["records"]] == [write["outcome"]["seq"], write["seq"]]
        assert (await page.get(f"api/records?device={POOL}&kind=write"))["records"] == []
        bounded = await page.get("api/records?limit=1")
        assert bounded["count"] == 1
        assert bounded["more"] is True
        assert (await page.get("api/records?limit=0"))["head"] == head  # the footer's ask
        status, refused = await _get(page, "api/records?kind=rumour")
        assert status == 400
        assert "no kind of record rumour" in refused["error"]
        status, refused = await _get(page, "api/records?since=yesterday")
        assert status == 400
        assert "ISO 8601" in refused["error"]
        later = await page.get("api/records?since=2999-01-01T00:00:00Z")
        assert later["records"] == []
        # The running page's overview carries the head, for the footer of every page.
        assert (await page.get("api/state"))["records"] == head


async def test_a_viewer_reads_records_but_may_not_verify_and_a_verification_is_signed(
    tmp_path: Path,
) -> None:
    _users(tmp_path)
    async with plant(tmp_path) as gateway:
        async with client(gateway.url) as viewer:
            await viewer.sign_in(VIEWER, VIEWER_PASSWORD)
            assert "records" in await viewer.get("api/records")
            form = await viewer.get(f"api/devices/{POOL}/verification")
            assert (form["point"], form["method"]) == ("concentration", "DPD")
            assert form["rule"]["name"] == "EPA 334.0"
            sensor = await _chlorine(viewer)
            asked = {"reference": sensor, "method": "DPD", "password": VIEWER_PASSWORD}
            status, body = await viewer.post(f"api/devices/{POOL}/verify", asked)
            assert status == 403
            assert "needs the operator role" in body["error"]

        async with client(gateway.url) as operator:
            await operator.sign_in(OPERATOR, OPERATOR_PASSWORD)
            asked = {
                "reference": round(sensor + 0.05, 3),
                "unit": form["unit"],
                "method": "DPD",
                "instrument": "pocket photometer 7",
                "reason": "weekly check",
            }
            path = f"api/devices/{POOL}/verify"
            status, body = await operator.post(path, asked)
            assert status == 403
            assert "signed with your password" in body["error"]
            status, body = await operator.post(path, {**asked, "password": VIEWER_PASSWORD})
            assert status == 403
            assert body["error"] == "wrong password: the verification was not done"
            status, body = await operator.post(path, {**asked, "password": OPERATOR_PASSWORD})
            assert status == 200, body
            assert body["passed"] is True
            assert body["sensor_value"] == pytest.approx(sensor, abs=1e-6)
            assert body["limit"] == pytest.approx(0.1)
            assert body["rule"]["name"] == "EPA 334.0"
            assert "calibration" not in body
            signed = body["record"]
            listed = await operator.get(f"api/records?device={POOL}&kind=verification")
            (shown,) = listed["records"]
            assert (shown["seq"], shown["result"]) == (signed, "passed")
            assert (shown["user"], shown["via"], shown["signed"]) == (OPERATOR, "page", True)
            assert shown["reason"] == "weekly check"
            assert shown["data"]["instrument"] == "pocket photometer 7"
        assert gateway.writes(CHLORINE) == []  # a verification writes nothing
    # The record as stored, read by the store itself after the gateway stopped.
    store = RecordStore(records_path(tmp_path / "state"), read_only=True)
    try:
        record = store.get(signed)
        assert record is not None
        assert record.kind == "verification"
        assert record.body["actor"] == {
            "user": OPERATOR,
            "via": "page",
            "detail": "127.0.0.1",
            "reason": "weekly check",
            "signed": True,
        }
        assert store.verify().intact
    finally:
        store.close()


async def test_a_failed_verification_offers_the_calibration_and_a_refusal_says_why(
    tmp_path: Path,
) -> None:
    _users(tmp_path)
    async with plant(tmp_path) as gateway, client(gateway.url) as operator:
        await operator.sign_in(OPERATOR, OPERATOR_PASSWORD)
        form = await operator.get(f"api/devices/{POOL}/verification")
        assert form["calibration"]["procedure"]
        sensor = await _chlorine(operator)
        signed: dict[str, object] = {"method": "DPD", "password": OPERATOR_PASSWORD}
        path = f"api/devices/{POOL}/verify"
        status, body = await operator.post(path, {**signed, "reference": round(sensor + 2, 3)})
        assert status == 200, body
        assert body["passed"] is False
        assert body["deviation"] == pytest.approx(-2, abs=1e-3)
        assert body["calibration"] == form["calibration"]  # the page's link to calibrate
        refusals: dict[str, dict[str, object]] = {
            "unknown keys ['colour']": {"reference": 0.5, "colour": "pink"},
            "more than the 60 min": {"reference": 0.5, "sampled_at": "2000-01-01T08:00+02:00"},
            "reference must be a number": {"reference": "half"},
        }
        for reason, asked in refusals.items():
            status, body = await operator.post(path, {**signed, **asked})
            assert status == 400
            assert reason in body["error"]
        status, body = await operator.post("api/devices/nowhere/verify", signed)
        assert status == 404
        listed = await operator.get("api/records?kind=verification")
        assert [r["result"] for r in listed["records"]] == ["failed-check"]  # refusals: none
        assert gateway.writes(CHLORINE) == []
