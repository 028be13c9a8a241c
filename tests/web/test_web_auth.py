"""Who may do what on the page: the password, sessions that expire, CSRF, loopback reads."""

from __future__ import annotations

import asyncio
import hashlib
import time
from typing import Any

import aiohttp
import pytest
from aiohttp import web
from aiohttp.test_utils import make_mocked_request
from prometheus_client import CollectorRegistry, generate_latest

from gateway.config import ConfigProblems, WebConfig, parse_config
from gateway.errors import ConfigError
from gateway.publish.prometheus import GatewayCollector
from gateway.shared.state import GatewayState
from gateway.web import Sessions, WebServer
from gateway.web.auth import MAX_FAILURES, WRONG_DELAY_S, host_allowed, is_loopback
from tests.mqtt_broker import free_port

CONFIG = "buses: [{name: basin, port: /dev/null}]\n"
PASSWORD = "s3cret"  # noqa: S105 - the tests' own


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def sessions(clock: Clock, password: str | None = PASSWORD) -> Sessions:
    config = WebConfig.model_validate(
        {"enabled": True, "password": password, "session_minutes": 10}
    )
    return Sessions.from_config(config, clock=clock)


def test_the_right_password_opens_a_session_that_expires_unless_it_writes() -> None:
    clock = Clock()
    keeper = sessions(clock)
    session = keeper.sign_in("  Ana   Lopes ", "s3cret", "127.0.0.1")
    assert session is not None
    assert session.who == "Ana Lopes"
    clock.now += 9 * 60
    assert keeper.find(session.token) is session  # read: no longer
    assert keeper.find(session.token, touch=True) is session  # a write: ten more minutes
    clock.now += 9 * 60
    assert keeper.find(session.token) is session
    clock.now += 1 * 60 + 1
    assert keeper.find(session.token) is None
    assert keeper.sign_in("ana", "s3cret", "127.0.0.1") is not None


def test_a_wrong_password_or_none_configured_opens_nothing() -> None:
    clock = Clock()
    assert sessions(clock).sign_in("eve", "s3cret ", "10.0.0.9") is None
    assert sessions(clock).sign_in("eve", "", "10.0.0.9") is None
    unset = sessions(clock, password=None)
    assert not unset.enabled
    assert unset.sign_in("eve", "", "10.0.0.9") is None


def test_the_password_may_be_given_as_its_sha256() -> None:
    digest = hashlib.sha256(b"s3cret").hexdigest().upper()
    config = parse_config(
        CONFIG + f"web: {{enabled: true, password_sha256: {digest}}}\n", environ={}
    )
    assert config.web.password_sha256 == digest.lower()
    assert Sessions.from_config(config.web).sign_in("ana", "s3cret", "::1") is not None
    with pytest.raises(ConfigProblems, match=r"web\.password_sha256"):
        parse_config(CONFIG + "web: {password_sha256: abc}\n", environ={})


def test_the_web_section_is_off_on_loopback_by_default_and_the_password_comes_from_the_environment() -> (
    None
):
    config = parse_config(CONFIG, environ={"GATEWAY_WEB__PASSWORD": "from-env"})
    assert (config.web.enabled, config.web.host, config.web.port) == (False, "127.0.0.1", 8080)
    assert config.web.password is not None
    assert config.web.password.get_secret_value() == "from-env"
    with pytest.raises(ConfigProblems, match=r"web\.colour"):
        parse_config(CONFIG + "web: {colour: blue}\n", environ={})


def test_the_csrf_token_is_the_sessions_own() -> None:
    session = sessions(Clock()).sign_in("ana", "s3cret", "127.0.0.1")
    assert session is not None
    assert session.csrf_ok(session.csrf)
    assert not session.csrf_ok(session.csrf[:-1])
    assert not session.csrf_ok(None)
    assert not session.csrf_ok("")


@pytest.mark.parametrize(
    ("remote", "local"),
    [
        ("127.0.0.1", True),
        ("127.8.9.1", True),
        ("::1", True),
        ("10.0.0.5", False),
        ("192.0.2.7", False),
        ("fe80::1%eth0", False),
        ("nonsense", False),
        (None, True),
    ],
)
def test_loopback_is_this_machine(remote: str | None, *, local: bool) -> None:
    assert is_loopback(remote) is local


class Peer:
    """The transport of a request from ``host``."""

    def __init__(self, host: str) -> None:
        self.host = host

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        return (self.host, 40000) if name == "peername" else default


async def _state(_request: web.Request) -> web.StreamResponse:
    return web.json_response({})


async def test_reading_from_another_machine_needs_a_session() -> None:
    config = WebConfig.model_validate({"enabled": True, "password": PASSWORD})
    server = WebServer(config, GatewayState(), {})
    guarded = server.guards.reader(_state)
    local = make_mocked_request("GET", "/api/state", transport=Peer("127.0.0.1"))
    assert (await guarded(local)).status == 200
    remote = make_mocked_request("GET", "/api/state", transport=Peer("192.0.2.7"))
    assert (await guarded(remote)).status == 401
    session = server.sessions.sign_in("ana", "s3cret", "192.0.2.7")
    assert session is not None
    signed = make_mocked_request(
        "GET",
        "/api/state",
        headers={"Cookie": f"gateway_session={session.token}"},
        transport=Peer("192.0.2.7"),
    )
    assert (await guarded(signed)).status == 200


async def test_a_port_that_is_taken_is_a_config_error_naming_web_port() -> None:
    first = WebServer(WebConfig.model_validate({"port": free_port()}), GatewayState(), {})
    await first.start()
    try:
        assert first.port
        taken = WebServer(WebConfig.model_validate({"port": first.port}), GatewayState(), {})
        with pytest.raises(ConfigError, match=r"web: cannot listen on 127\.0\.0\.1:") as info:
            await taken.start()
        assert info.value.key == "web.port"
    finally:
        await first.stop()


def test_a_session_slides_with_its_writes_and_is_held_while_its_calibration_runs() -> None:
    clock = Clock()
    keeper = sessions(clock)  # ten minutes
    session = keeper.sign_in("ana", PASSWORD, "127.0.0.1")
    assert session is not None
    keeper.hold(session.token)  # a calibration started
    clock.now += 60 * 60
    assert keeper.find(session.token) is session  # an hour later: still held
    keeper.release(session.token)  # it ended: ten minutes from now
    clock.now += 9 * 60
    assert keeper.find(session.token) is session
    clock.now += 61
    assert keeper.find(session.token) is None


async def _server(config: dict[str, Any], state: GatewayState | None = None) -> WebServer:
    server = WebServer(
        WebConfig.model_validate({"enabled": True, "port": free_port(), **config}),
        state or GatewayState(),
        {},
    )
    await server.start()
    return server


@pytest.mark.parametrize(
    ("host", "status"),
    [
        ("127.0.0.1:{port}", 200),
        ("127.0.0.1", 200),
        ("localhost:{port}", 200),
        ("LOCALHOST.:{port}", 200),
        ("gateway.plant.example:{port}", 200),
        ("a.basin.example", 200),
        ("basin.example", 421),
        ("evil.example", 421),
        ("evil.example:{port}", 421),
        ("10.0.0.5:{port}", 421),
        ("gateway.plant.example.evil.example", 421),
    ],
)
async def test_the_page_answers_only_to_its_own_host_names(host: str, status: int) -> None:
    server = await _server({"allowed_hosts": ["gateway.plant.example", "*.basin.example"]})
    try:
        async with aiohttp.ClientSession() as client:
            headers = {"Host": host.format(port=server.port)}
            for path in ("/api/state", "/"):
                async with client.get(f"{server.url}{path[1:]}", headers=headers) as response:
                    assert response.status == status, path
                    if status == 421:
                        text = await response.text()
                        assert "does not answer to the host name" in text
                        assert "web.allowed_hosts" in text
    finally:
        await server.stop()


def test_localhost_names_are_accepted_only_from_this_machine() -> None:
    def allowed(header: str | None, remote: str, listen: str = "0.0.0.0") -> bool:  # noqa: S104
        return host_allowed(header, allowed=(), listen=listen, local="192.0.2.1", remote=remote)

    assert allowed("localhost:8080", "127.0.0.1")
    assert not allowed("localhost:8080", "192.0.2.7")
    assert allowed("192.0.2.1:8080", "192.0.2.7")  # the address the client connected to
    assert allowed("[::ffff:192.0.2.1]:8080", "192.0.2.7")
    assert not allowed("192.0.2.9:8080", "192.0.2.7")
    assert allowed("gateway.local", "192.0.2.7", listen="gateway.local")
    assert allowed(None, "192.0.2.7")  # HTTP/1.0, no browser


async def test_parallel_guesses_take_the_throttles_time_and_lock_the_address_out(
    caplog: pytest.LogCaptureFixture,
) -> None:
    state = GatewayState()
    server = await _server({"password": PASSWORD}, state)
    wrong = {"name": "eve", "password": "guess"}
    try:
        async with aiohttp.ClientSession() as client:

            async def guess() -> int:
                async with client.post(f"{server.url}api/login", json=wrong) as response:
                    return response.status

            started = time.monotonic()
            statuses = await asyncio.gather(*(guess() for _ in range(20)))
            elapsed = time.monotonic() - started
            # Checked one at a time, each wrong one costing its delay: five, then locked out.
            assert statuses.count(403) == MAX_FAILURES
            assert statuses.count(429) == 20 - MAX_FAILURES
            assert elapsed >= MAX_FAILURES * WRONG_DELAY_S
            # Locked out: even the right password from that address is turned away ...
            right = {"name": "ana", "password": PASSWORD}
            async with client.post(f"{server.url}api/login", json=right) as response:
                assert response.status == 429
                assert int(response.headers["Retry-After"]) > 0
                assert "too many wrong passwords" in (await response.json())["error"]
        # ... while another address signs in at once.
        other = aiohttp.TCPConnector(local_addr=("127.0.0.2", 0))
        async with (
            aiohttp.ClientSession(connector=other) as client,
            client.post(f"{server.url}api/login", json=right) as response,
        ):
            assert response.status == 200
            assert "max-age" not in response.headers["Set-Cookie"].lower()  # it slides
    finally:
        await server.stop()
    assert "web: 127.0.0.1 locked out for 300 s after 5 wrong passwords" in caplog.text
    web = state.snapshot().web
    assert web.sign_ins["wrong"] == MAX_FAILURES
    assert web.sign_ins["ok"] == 1
    assert web.lockouts == 1
    exposition = generate_latest(_registry(state)).decode()
    assert "gateway_web_lockouts_total 1.0" in exposition
    assert "gateway_web_locked_out_addresses 1.0" in exposition
    assert 'gateway_web_sign_ins_total{outcome="wrong"} 5.0' in exposition


def _registry(state: GatewayState) -> CollectorRegistry:
    registry = CollectorRegistry()
    registry.register(GatewayCollector(state))
    return registry
