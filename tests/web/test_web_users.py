"""Named users on the running page: roles refused and allowed, the shared password, signatures.

The gateway runs with its page against the simulator (``tests/web_rig.plant``), the users
file in its state directory; the requests are the page's own, sent by an HTTP client with
a cookie jar.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import TYPE_CHECKING, Any

import aiohttp
import pytest

from gateway.records.actor import SHARED_PASSWORD, Via
from gateway.web.users import USERS_FILE, Role, UserBook
from tests.web_rig import CHLORINE, NAMES, OXYGEN, PASSWORD, plant

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Callable
    from pathlib import Path

pytestmark = [pytest.mark.line, pytest.mark.timeout(120)]

OPERATOR = "ana"
OPERATOR_PASSWORD = "basin at dawn"  # noqa: S105 - the tests' own
VIEWER = "vic"
VIEWER_PASSWORD = "reads only please"  # noqa: S105 - the tests' own
PRESSURE = f"api/devices/{NAMES[OXYGEN]}/points/compensation_pressure"


def _users(tmp_path: Path) -> None:
    """The users file where the plant's gateway looks for it: its state directory."""
    book = UserBook(tmp_path / "state" / USERS_FILE)
    book.add(OPERATOR, Role.OPERATOR, OPERATOR_PASSWORD)
    book.add(VIEWER, Role.VIEWER, VIEWER_PASSWORD)


class Client:
    """One browser's worth of the page: its cookie, its CSRF token."""

    def __init__(self, http: aiohttp.ClientSession, url: str) -> None:
        self.http = http
        self.url = url
        self.csrf = ""

    async def sign_in(self, name: str, password: str) -> dict[str, Any]:
        status, body = await self.post("api/login", {"name": name, "password": password})
        assert status == 200, body
        self.csrf = str(body["csrf"])
        return body

    async def post(self, path: str, body: object) -> tuple[int, dict[str, Any]]:
        headers = {"X-CSRF-Token": self.csrf} if self.csrf else {}
        async with self.http.post(f"{self.url}{path}", json=body, headers=headers) as response:
            return response.status, await response.json()

    async def get(self, path: str) -> dict[str, Any]:
        async with self.http.get(f"{self.url}{path}") as response:
            assert response.status == 200
            data: dict[str, Any] = await response.json()
            return data


@contextlib.asynccontextmanager
async def client(url: str) -> AsyncIterator[Client]:
    # The page is at 127.0.0.1: aiohttp keeps cookies of an address only if told to.
    async with aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as http:
        yield Client(http, url)


async def test_a_viewer_is_refused_a_write_with_the_role_needed_and_an_operator_writes(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    _users(tmp_path)
    async with plant(tmp_path) as gateway:
        sensor = gateway.device(OXYGEN)
        async with client(gateway.url) as viewer:
            signed = await viewer.sign_in("Vic", VIEWER_PASSWORD)  # a phone's capital
            assert (signed["user"], signed["role"]) == (VIEWER, "viewer")
            session = await viewer.get("api/session")
            assert (session["who"], session["role"], session["can_write"]) == (
                VIEWER,
                "viewer",
                False,
            )
            status, body = await viewer.post(PRESSURE, {"value": "1003.5"})
            assert status == 403
            assert "needs the operator role" in body["error"]
            assert "vic is a viewer" in body["error"]
            calibration = {
                "device": NAMES[CHLORINE],
                "procedure": "slope",
                "inputs": {"reference": "0.5"},
                "password": VIEWER_PASSWORD,
            }
            status, body = await viewer.post("api/calibrations", calibration)
            assert status == 403
            assert "operator role" in body["error"]
            # Reading every register is reading: a viewer may.
            status, body = await viewer.post(f"api/devices/{NAMES[OXYGEN]}/read", {})
            assert status == 200, body
        assert sensor.get("compensation_pressure") != 1003.5
        assert gateway.writes(OXYGEN) == []
        refusals = [r for r in caplog.records if "role is needed" in r.getMessage()]
        assert refusals
        assert all(r.levelname == "WARNING" for r in refusals)
        async with client(gateway.url) as operator:
            signed = await operator.sign_in(OPERATOR, OPERATOR_PASSWORD)
            assert (signed["user"], signed["role"]) == (OPERATOR, "operator")
            status, body = await operator.post(
                PRESSURE, {"value": "1003.5", "reason": "barometer of the plant"}
            )
            assert status == 200, body
            assert body["value"] == 1003.5
        assert sensor.get("compensation_pressure") == 1003.5


async def test_a_wrong_password_or_an_unknown_user_opens_no_session(tmp_path: Path) -> None:
    _users(tmp_path)
    async with plant(tmp_path, password=None) as gateway, client(gateway.url) as page:
        for name, password in ((OPERATOR, VIEWER_PASSWORD), ("zoe", OPERATOR_PASSWORD)):
            status, body = await page.post("api/login", {"name": name, "password": password})
            assert status == 403
            assert body["error"] == "wrong name or password"
        assert not (await page.get("api/session"))["signed_in"]
        assert (await page.get("api/session"))["can_sign_in"]  # users, and no shared password


async def test_the_shared_password_still_signs_in_and_writes_as_an_operator(
    tmp_path: Path,
) -> None:
    _users(tmp_path)  # a plant with users may keep the shared password too
    async with plant(tmp_path) as gateway, client(gateway.url) as page:
        signed = await page.sign_in("Ana Lopes", PASSWORD)
        assert (signed["who"], signed["user"], signed["role"]) == (
            "Ana Lopes",
            SHARED_PASSWORD,
            "operator",
        )
        session = await page.get("api/session")
        assert session["shared"] is True
        assert session["can_write"] is True
        status, body = await page.post(PRESSURE, {"value": "1001.25"})
        assert status == 200, body
        assert gateway.device(OXYGEN).get("compensation_pressure") == 1001.25
        # A write that says it is signed is checked: a wrong password writes nothing.
        status, body = await page.post(PRESSURE, {"value": "990", "password": "guess"})
        assert status == 403
        assert body["error"] == "wrong password: the write was not done"
        assert gateway.device(OXYGEN).get("compensation_pressure") == 1001.25


async def test_a_calibration_is_started_only_with_the_password_again_and_its_task_acts_signed(
    tmp_path: Path,
) -> None:
    _users(tmp_path)
    async with plant(tmp_path) as gateway, client(gateway.url) as page:
        await page.sign_in(OPERATOR, OPERATOR_PASSWORD)
        calibration: dict[str, object] = {
            "device": NAMES[CHLORINE],
            "procedure": "slope",
            "inputs": {"reference": "0.5", "samples": "1"},
            "reason": "weekly check, DPD 0.50",
        }
        status, body = await page.post("api/calibrations", calibration)
        assert status == 403
        assert "signed with your password: give it again" in body["error"]
        status, body = await page.post(
            "api/calibrations", {**calibration, "password": VIEWER_PASSWORD}
        )
        assert status == 403
        assert body["error"] == "wrong password: the calibration was not done"
        assert (await page.get(f"api/calibrations?device={NAMES[CHLORINE]}"))["runs"] == []
        status, body = await page.post(
            "api/calibrations", {**calibration, "password": OPERATOR_PASSWORD}
        )
        assert status == 201, body
        # The run's task was created under the user's actor and inherited it: the flow's
        # writes, long after this request was answered, are recorded as the user's, signed.
        run_id = str(body["id"])
        run = await _until(
            page, f"api/calibrations/{run_id}", lambda r: r["actor"]["user"] != "unattributed"
        )
        assert run["actor"] == {
            "user": OPERATOR,
            "via": str(Via.PAGE),
            "detail": "127.0.0.1",
            "reason": "weekly check, DPD 0.50",
            "signed": True,
        }
        status, _ = await page.post(f"api/calibrations/{run_id}/cancel", {})
        assert status == 200
    assert gateway.writes(CHLORINE) == []  # nothing confirmed: nothing written


async def _until(page: Client, path: str, test: Callable[[Any], object]) -> dict[str, Any]:
    """GET ``path`` until ``test`` holds of its JSON; that JSON."""
    async with asyncio.timeout(30):
        while True:
            data = await page.get(path)
            if test(data):
                return data
            await asyncio.sleep(0.05)
