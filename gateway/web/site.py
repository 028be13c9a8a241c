"""The page's HTTP server: aiohttp in the gateway's own event loop, one named task.

Routes (JSON unless said; ``R`` read: loopback or a session; ``W`` write: a session and
its CSRF token in ``X-CSRF-Token``, and a same-origin ``Origin`` if the browser sends one)::

    GET  /                                  the page (static: index.html, app.js, style.css)
    GET  /api/session                       who is signed in, their role, the CSRF token
    POST /api/login  {name, password}       a session (cookie), or 403
    POST /api/logout
    GET  /api/state                      R  lines and devices with live values, bus health
    GET  /api/events                     R  the same, as server-sent events, every second
    GET  /api/care                       R  sensor care: every device's document, most urgent
                                            first, with the calibration it asks for
    GET  /api/devices/{device}           R  identity, register map, procedures
    POST /api/devices/{device}/points/{point}  W  {value, reason?, password?}: a write
                                            through SafeWriter (signed if password is given)
    POST /api/devices/{device}/read      W* every point read now (queued ahead of polls)
    POST /api/calibrations               W  {device, procedure, inputs, password, reason?}:
                                            a guided run, signed with the password again
    GET  /api/calibrations?device=NAME   R  the runs under way (of a device)
    GET  /api/calibrations/{id}          R  its steps, question, outcome
    POST /api/calibrations/{id}/answer   W  {confirm: bool}: only from the run's session
    POST /api/calibrations/{id}/take-over W  the run becomes this session's
    POST /api/calibrations/{id}/cancel   W
    POST /api/lines/{bus}/scan           W  a scan of the line, its polling paused
    GET  /api/lines/{bus}/scan           R  the scan's progress and report
    GET  /api/records?device=&kind=&since=&until=&limit=
                                         R  the records chosen, newest first (500 unless
                                            limit says), the chain's head and verdict
    GET  /api/devices/{device}/verification  R  what the verification form starts from
    POST /api/devices/{device}/verify    W  {reference, unit?, method, instrument?,
                                            sampled_at?, reason?, password}: a grab-sample
                                            verification, signed; its outcome, or why not

``W`` needs an operator's or an admin's session: a viewer's is refused with 403 and a
message naming the role needed (``W*``: a viewer's too, it only reads). Every write and
calibration is logged with who did it (the signed-in user, or the name given with the
shared password) and from where, and runs under that user's
:class:`~gateway.records.actor.Actor` (:func:`~gateway.records.actor.acting`), which the
records name. A calibration is signed (21 CFR Part 11 §11.200: both components, name and
password, at the first signing of a session): its request carries the user's password
again, refused with 403 without it or with a wrong one; a verification likewise; a write is
signed when its request carries the password. Without a record store (``records``) the
records answer 404; without a verifier, verifications answer 503. Every request first
passes the ``Host`` check (:func:`host_allowed`): a name the page does not answer to gets
421, so a DNS-rebinding page cannot read it through a browser on this machine. Sign-ins
and signatures pass the :class:`SignInThrottle`, their scrypt checks in a thread so the
loop goes on polling.

This module holds the application, the ``Host`` check, the live views, the event stream
and the scans; the other routes are grouped by what they do, each in its own module
behind :mod:`gateway.web.guards`: sign-in (:mod:`~gateway.web.sign_in`), writes
(:mod:`~gateway.web.writes`), calibrations (:mod:`~gateway.web.calibration_routes`),
records and verifications (:mod:`~gateway.web.record_routes`).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from importlib import resources
from typing import TYPE_CHECKING, Final

from aiohttp import web

from gateway.errors import CommandRejectedError, ConfigError
from gateway.web.auth import (
    Sessions,
    SignInThrottle,
    host_allowed,
    is_loopback,
)
from gateway.web.calibration import Calibrations, procedures_for
from gateway.web.calibration_routes import CalibrationRoutes
from gateway.web.care import care_documents
from gateway.web.guards import Guards, error, json_body, who
from gateway.web.live import overview, register_map
from gateway.web.record_routes import RecordRoutes
from gateway.web.records import head_view
from gateway.web.sign_in import SignInRoutes
from gateway.web.users import Role
from gateway.web.writes import WriteRoutes

if TYPE_CHECKING:
    from collections.abc import Awaitable, Callable, Mapping

    from gateway.config import WebConfig
    from gateway.control.verification import Verifier
    from gateway.control.writes import SafeWriter
    from gateway.records import RecordStore
    from gateway.shared.state import GatewayState
    from gateway.web.scan import LineScans
    from gateway.web.users import UserBook

    Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]

_LOGGER = logging.getLogger(__name__)

EVENT_INTERVAL_S: Final = 1.0
MAX_REFUSED: Final = 256  # Host names remembered as refused, to warn once per name
SHUTDOWN_S: Final = 3.0
STATIC_FILES: Final = {
    "index.html": "text/html",
    "app.js": "text/javascript",
    "style.css": "text/css",
    "favicon.svg": "image/svg+xml",
}
_SECURITY_HEADERS: Final = {
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "same-origin",
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; "
    "style-src 'self'; script-src 'self'; connect-src 'self'; frame-ancestors 'none'",
    "Cache-Control": "no-store",
}


def _static(name: str) -> bytes:
    return resources.files("gateway.web").joinpath("static", name).read_bytes()


class WebServer:
    """The page, served from the gateway's loop while :meth:`run` runs."""

    def __init__(
        self,
        config: WebConfig,
        state: GatewayState,
        writers: Mapping[str, SafeWriter],
        *,
        scans: LineScans | None = None,
        sessions: Sessions | None = None,
        calibrations: Calibrations | None = None,
        throttle: SignInThrottle | None = None,
        users: UserBook | None = None,
        records: RecordStore | None = None,
        verifier: Verifier | None = None,
        event_interval_s: float = EVENT_INTERVAL_S,
    ) -> None:
        """Serve ``state``; writes and calibrations through ``writers`` (by device name).

        ``sessions`` and ``calibrations``: a former page's, kept by a reload (a calibration
        under way goes on, its operator still signed in). ``users``: the users file
        (without it, only the shared password signs in). ``records``: the record store the
        records view reads (its head on every page); ``verifier``: the gateway's
        grab-sample verifications.
        """
        self.config = config
        self.state = state
        self.writers = writers
        self.scans = scans
        self.records = records
        self.verifier = verifier
        self.sessions = sessions or Sessions.from_config(config, users=users)
        self.throttle = throttle or SignInThrottle()
        if calibrations is None:
            calibrations = Calibrations(writers, sessions=self.sessions)
        calibrations.confirm_timeout_s = config.confirm_minutes * 60
        self.calibrations = calibrations
        self.guards = Guards(self.sessions, self.throttle)
        self._writes = WriteRoutes(writers, state, self.guards)
        self._runs = CalibrationRoutes(calibrations, self.guards)
        self._record_routes = RecordRoutes(records, verifier, writers, state, self.guards)
        self._sign_in = SignInRoutes(config, state, calibrations, self.guards)
        self._allowed_hosts = frozenset(config.allowed_hosts)
        self._refused_hosts: set[str] = set()
        state.web.enabled = True
        self.event_interval_s = event_interval_s
        self.port: int | None = None  # the port bound, once started
        self._closing = asyncio.Event()
        self._latest: tuple[float, str] = (0.0, "")
        self._runner: web.AppRunner | None = None

    # --- running ----------------------------------------------------------------------

    def app(self) -> web.Application:
        """The aiohttp application with every route."""
        app = web.Application(middlewares=[self._headers, self._host_check])
        get, post = web.get, web.post
        read, write, runs = self.guards.reader, self.guards.writer, self._runs
        app.add_routes(
            [
                get("/", self._index),
                get("/static/{name}", self._asset),
                get("/api/session", self._sign_in.session_info),
                post("/api/login", self._sign_in.login),
                post("/api/logout", self._sign_in.logout),
                get("/api/state", read(self._state)),
                get("/api/events", read(self._events)),
                get("/api/care", read(self._care)),
                get("/api/devices/{device}", read(self._device)),
                post("/api/devices/{device}/points/{point}", write(self._writes.write)),
                post("/api/devices/{device}/read", write(self._writes.read_all, needs=Role.VIEWER)),
                post("/api/calibrations", write(runs.start)),
                get("/api/calibrations", read(runs.under_way)),
                get("/api/calibrations/{id}", read(runs.one)),
                post("/api/calibrations/{id}/answer", write(runs.answer)),
                post("/api/calibrations/{id}/take-over", write(runs.take_over)),
                post("/api/calibrations/{id}/cancel", write(runs.cancel)),
                post("/api/lines/{bus}/scan", write(self._start_scan)),
                get("/api/lines/{bus}/scan", read(self._scan)),
                get("/api/records", read(self._record_routes.records)),
                get("/api/devices/{device}/verification", read(self._record_routes.verification)),
                post("/api/devices/{device}/verify", write(self._record_routes.verify)),
            ]
        )
        return app

    async def start(self) -> None:
        """Listen on the configured host and port."""
        self._runner = web.AppRunner(
            self.app(), access_log=None, shutdown_timeout=SHUTDOWN_S, handle_signals=False
        )
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.config.host, self.config.port)
        try:
            await site.start()
        except OSError as exc:
            await self._runner.cleanup()
            self._runner = None
            where = f"{self.config.host}:{self.config.port}"
            raise ConfigError(f"web: cannot listen on {where}: {exc}", key="web.port") from exc
        bound = self._runner.addresses
        self.port = int(bound[0][1]) if bound else self.config.port
        if not self.sessions.enabled:
            _LOGGER.warning(
                "web: no users (gateway users add) and no password (GATEWAY_WEB__PASSWORD): "
                "the page is read-only, from this machine only"
            )
        _LOGGER.info("web: the page is at %s", self.url)

    @property
    def url(self) -> str:
        """Where a browser on this machine finds the page."""
        host = self.config.host
        if host in {"0.0.0.0", "::"}:  # noqa: S104 - naming it, not binding it
            host = "127.0.0.1"
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port or self.config.port}/"

    async def stop(self, *, keep_calibrations: bool = False) -> None:
        """Close the event streams, let waiting calibrations decline, stop listening.

        ``keep_calibrations``: a reload rebuilds the page; its runs go on under the next.
        Stopped once: :meth:`run`'s end, after a reload's stop, changes nothing more.
        """
        if self._closing.is_set():
            return
        self._closing.set()
        if not keep_calibrations:
            await self.calibrations.close()
        if self.scans is not None:
            await self.scans.close()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    async def run(self, stop: asyncio.Event | None = None) -> None:
        """Serve (starting if need be) until cancelled or ``stop`` is set, then stop."""
        if self._runner is None:
            await self.start()
        try:
            await (stop or asyncio.Event()).wait()
        finally:
            await self.stop()

    # --- guards -----------------------------------------------------------------------

    @web.middleware
    async def _headers(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        response = await handler(request)
        if not response.prepared:
            for name, value in _SECURITY_HEADERS.items():
                response.headers.setdefault(name, value)
        return response

    @web.middleware
    async def _host_check(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        """Answer only to the configured names, the listen address and localhost here."""
        sockname = request.transport.get_extra_info("sockname") if request.transport else None
        local = str(sockname[0]) if isinstance(sockname, tuple) and sockname else None
        header = request.headers.get("Host")
        if host_allowed(
            header,
            allowed=self._allowed_hosts,
            listen=self.config.host,
            local=local,
            remote=request.remote,
        ):
            return await handler(request)
        # The first request of a refused name is a warning; a page polling it, quiet.
        first = header not in self._refused_hosts and len(self._refused_hosts) < MAX_REFUSED
        self._refused_hosts.add(header or "")
        _LOGGER.log(
            logging.WARNING if first else logging.DEBUG,
            "web: %s %s from %s refused: Host %r is not a name of this gateway (web.allowed_hosts)",
            request.method,
            request.path,
            request.remote,
            header,
        )
        return web.Response(
            status=421,
            text=f"This gateway does not answer to the host name {header!r}. If that is "
            "its name, add it to web.allowed_hosts in the gateway's config.\n",
        )

    # --- the page ---------------------------------------------------------------------

    async def _index(self, _request: web.Request) -> web.StreamResponse:
        return web.Response(body=_static("index.html"), content_type="text/html", charset="utf-8")

    async def _asset(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info["name"]
        kind = STATIC_FILES.get(name)
        if kind is None:
            raise web.HTTPNotFound
        return web.Response(body=_static(name), content_type=kind)

    # --- reading ----------------------------------------------------------------------

    def _overview(self) -> str:
        """The overview as JSON, made at most once per half interval for every reader."""
        now = time.monotonic()
        made, text = self._latest
        if now - made >= self.event_interval_s / 2 or not text:
            paused = self.scans.paused() if self.scans is not None else {}
            data = overview(self.state, paused)
            if self.records is not None:  # the chain's head, on every page
                head = self.records.head
                data["records"] = head_view(head.seq, head.hash)
            text = json.dumps(data, separators=(",", ":"))
            self._latest = (now, text)
        return text

    async def _state(self, _request: web.Request) -> web.StreamResponse:
        return web.Response(text=self._overview(), content_type="application/json")

    async def _events(self, request: web.Request) -> web.StreamResponse:
        response = web.StreamResponse(
            headers={
                "Content-Type": "text/event-stream",
                "Cache-Control": "no-cache",
                "X-Accel-Buffering": "no",
            }
        )
        await response.prepare(request)
        local = is_loopback(request.remote)
        with contextlib.suppress(ConnectionError):
            while not self._closing.is_set():
                if not local and self.guards.session_of(request) is None:
                    break  # the session ended: reading from elsewhere needs a new one
                await response.write(f"event: state\ndata: {self._overview()}\n\n".encode())
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(self.event_interval_s):
                        await self._closing.wait()
        return response

    async def _care(self, _request: web.Request) -> web.StreamResponse:
        return web.json_response(care_documents(self.state))

    async def _device(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info["device"]
        info = next((i for i in self.state.devices.values() if i.name == name), None)
        writer = self.writers.get(name)
        if info is None or writer is None:
            return error(404, f"no device {name!r}")
        profile = writer.link.profile
        data = register_map(
            info,
            profile,
            self.state,
            writable_by_page=self.sessions.enabled,
            flash_allowed=writer.policy.allowed,
        )
        data["procedures"] = [p.as_dict() for p in procedures_for(profile)]
        return web.json_response(data)

    # --- scanning ---------------------------------------------------------------------

    async def _start_scan(self, request: web.Request) -> web.StreamResponse:
        if self.scans is None:
            return error(404, "scans are not available")
        try:
            body = await json_body(request)
            addresses = str(body.get("addresses") or "1-247")
            job = self.scans.start(request.match_info["bus"], who(request), addresses)
        except CommandRejectedError as exc:
            return error(409, str(exc))
        return web.json_response(job.as_dict(), status=201)

    async def _scan(self, request: web.Request) -> web.StreamResponse:
        job = self.scans.latest(request.match_info["bus"]) if self.scans is not None else None
        if job is None:
            return error(404, "no scan of this line yet")
        return web.json_response(job.as_dict())
