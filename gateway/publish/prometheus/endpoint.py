"""The HTTP server: ``/metrics`` from the collector's registry, ``/healthz`` and ``/care``."""

from __future__ import annotations

import copy
import ctypes
import ipaddress
import itertools
import json
import logging
import os
import selectors
import socket
import socketserver
import sys
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import TYPE_CHECKING, Final, Self
from urllib.parse import urlsplit

from prometheus_client import CollectorRegistry
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4, generate_latest
from prometheus_client.registry import Collector

from gateway.care import care_order
from gateway.errors import PublishError
from gateway.line.stats import ErrorKind
from gateway.publish.prometheus.clock import clock_health
from gateway.publish.prometheus.collector import GatewayCollector
from gateway.publish.prometheus.identity_mismatch import identity_report
from gateway.publish.prometheus.selection import Selection
from gateway.publish.prometheus.storage import storage_health

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Iterator, Sequence

    from prometheus_client.metrics_core import Metric

    from gateway.config.prometheus import PrometheusConfig
    from gateway.shared.state import GatewayState

_LOGGER = logging.getLogger(__name__)

DEFAULT_HOST: Final = "0.0.0.0"  # noqa: S104 - prometheus.host's documented default
DEFAULT_PORT: Final = 9108  # prometheus.port's default, as in the product contract
MAX_POST_BYTES: Final = 16_384  # a verification's request is a few hundred bytes
STOP_TIMEOUT_S: Final = 2.0  # wait for the server thread to end after shutdown
REQUEST_TIMEOUT_S: Final = 10.0  # socket timeout of one HTTP connection
_INTERNAL_ERROR: Final = (HTTPStatus.INTERNAL_SERVER_ERROR, "text/plain", [b"internal error\n"])


# --- /metrics --------------------------------------------------------------------------------


class _OneFamily(Collector):
    """A registry of one family, for the exposition of that family alone."""

    def __init__(self, metric: Metric) -> None:
        self._metric = metric

    def collect(self) -> Iterable[Metric]:
        return (self._metric,)


def exposition(registry: CollectorRegistry) -> list[bytes]:
    """``generate_latest``'s text, in pieces of at most ``PIECE_SAMPLES`` samples.

    The same bytes, but never the whole scrape at once as the lines of every family, their
    join and its encoding: at 16 buses x 16 devices with every poll group and the old names
    a scrape is some 55,000 lines (6 MB; 12,000 and 1.1 MB by default), and making it in
    one piece held three copies of it, which the process kept as resident memory. The
    collector builds the families one by one as they are asked for; a large family (the
    values' ages: some 23,000 lines there) is written a piece at a time, each piece's lines
    freed as soon as it is encoded.
    """
    return [piece for metric in registry.collect() for piece in _pieces(metric)]


PIECE_SAMPLES: Final = 2000  # lines per piece: some 200 kB, small objects freed at once


def _pieces(metric: Metric) -> Iterator[bytes]:
    """One family's exposition: its header with its first samples, then the rest in pieces.

    Only a gauge is cut: other types put some samples apart (``_created`` at the end), so
    their text is made in one piece. Each piece is ``generate_latest``'s text of a copy of
    the family holding those samples, without the header after the first.
    """
    if metric.type != "gauge":
        yield generate_latest(_OneFamily(metric))
        return
    samples = iter(metric.samples)
    first = True
    while True:
        chunk = list(itertools.islice(samples, PIECE_SAMPLES))
        if not chunk and not first:
            return
        part = copy.copy(metric)
        part.samples = chunk
        text = generate_latest(_OneFamily(part))
        # The header is two lines (newlines in the documentation are escaped): once.
        yield text if first else text.split(b"\n", 2)[2]
        first = False
        if len(chunk) < PIECE_SAMPLES:
            return


def _malloc_trim() -> Callable[[], object] | None:
    """The C library's ``malloc_trim(0)``, if it has one (glibc; musl has not)."""
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = (ctypes.c_size_t,)
    trim.restype = ctypes.c_int
    return lambda: trim(0)


_TRIM: Final = _malloc_trim()


def release_free_memory() -> None:
    """Give the C heap's free pages back to the system, after a scrape.

    A scrape at 16 x 16 makes up to 6 MB of text and the lists and strings it is made of;
    freed, what lies in the middle of the heap stays resident (the C library returns only
    the top of its heap by itself), and so does what the start's burst of messages left
    (every point read at once). Once per scrape (every 15 s or so), in the scrape's own
    thread, the free pages go back: some milliseconds of this thread, none of the buses'.
    Python's own small objects live in arenas of their own, which this does not touch.
    """
    if _TRIM is not None:
        _TRIM()


# --- /healthz --------------------------------------------------------------------------------


def health_report(state: GatewayState) -> tuple[bool, dict[str, object]]:
    """Whether the gateway is healthy, and the ``/healthz`` body that says why (not).

    Healthy: every bus port is open, and MQTT is connected or buffering within its bound.
    A device that does not answer is the device's problem, not the gateway's: it shows
    in ``devices_online`` and the metrics, not in the status; so does a device whose
    pinned serial number another sensor answers with, listed under ``identity`` with
    both serials and what to do.
    """
    snapshot = state.snapshot()
    health = snapshot.health()
    availability = {(h.bus, h.device): h.online for h in health}
    reasons: list[str] = []
    buses: dict[str, object] = {}
    for bus, stats in sorted(snapshot.lines.items()):
        devices = [info for info in snapshot.devices.values() if info.bus == bus]
        online = sum(
            1 for info in devices if availability.get((bus, info.name), info.online) is True
        )
        buses[bus] = {
            "port_open": stats.port_open,
            # Why not (line/transports/port_diagnosis.PortReason: missing,
            # permission_denied, in_use, no_rs485_mode, driver_error) and the message with
            # the remedy; null while open.
            "port_problem": None if stats.port_open else stats.port_problem,
            "port_error": None if stats.port_open else (stats.port_error or None),
            "latency_timer_s": stats.latency_timer_s,
            "devices_online": online,
            "devices": len(devices),
            "line_noise": stats.noisy,  # the line never fell silent before the last request
            "no_silence_errors": sum(
                # dict(): one copy under the GIL; the bus task counts on meanwhile
                n
                for (_, kind), n in dict(stats.errors).items()
                if kind == ErrorKind.NO_SILENCE
            ),
        }
        if not stats.port_open:
            why = f": {stats.port_problem}: {stats.port_error}" if stats.port_problem else ""
            reasons.append(f"bus {bus}: port not open ({stats.port_failures} failures){why}")
        elif stats.noisy is not None:
            reasons.append(f"bus {bus}: {stats.noisy}")
    mqtt = snapshot.mqtt
    if mqtt.identity_conflict is not None:
        reasons.append(f"mqtt: {mqtt.identity_conflict}")
    elif not mqtt.healthy:
        why = f": {mqtt.last_error}" if mqtt.last_error else ""
        reasons.append(
            f"mqtt: not connected and the queue is full ({mqtt.queue_depth}/{mqtt.queue_max}){why}"
        )
    if snapshot.sparkplug.identity_conflict is not None:
        reasons.append(f"sparkplug: {snapshot.sparkplug.identity_conflict}")
    storage_reasons, storage = storage_health(snapshot)
    reasons.extend(storage_reasons)
    body: dict[str, object] = {
        "status": "unhealthy" if reasons else "ok",
        "reasons": reasons,
        "buses": buses,
        "identity": identity_report(health),
        **_shared_bus(snapshot),
        "storage": storage,
        "clock": clock_health(snapshot),  # said, not a reason: a restart cannot fix it
        "records": _records_head(snapshot),
        "config": {
            # A refused reload leaves the gateway running its previous config: not
            # unhealthy, but said here with the file's problems (and in the metrics).
            "last_reload_successful": snapshot.config.last_reload_ok,
            "reloads": snapshot.config.reloads,
            "problems": list(snapshot.config.problems),
            "applied": snapshot.config.applied,
        },
        "mqtt": {
            "enabled": mqtt.enabled,
            "connected": mqtt.connected,
            "healthy": mqtt.healthy,
            "queue_depth": mqtt.queue_depth,
            "queue_max": mqtt.queue_max,
            "dropped": mqtt.dropped,
            "published": mqtt.published,
            "last_error": mqtt.last_error,
            "server": mqtt.server,
            "servers": list(mqtt.servers),
            "switches": mqtt.switches,
            "identity_conflict": mqtt.identity_conflict,
        },
    }
    sparkplug = snapshot.sparkplug
    if sparkplug.enabled:
        body["sparkplug"] = {
            "connected": sparkplug.connected,
            "host_online": sparkplug.host_online,
            "bd_seq": sparkplug.bd_seq,
            "births": sparkplug.births,
            "published": sparkplug.published,
            "queue_depth": sparkplug.queue_depth,
            "dropped": sparkplug.dropped,
            "last_error": sparkplug.last_error,
            "server": sparkplug.server,
            "servers": list(sparkplug.servers),
            "switches": sparkplug.switches,
            "identity_conflict": sparkplug.identity_conflict,
        }
    return not reasons, body


def _shared_bus(snapshot: GatewayState) -> dict[str, object]:
    """The shared bus's addresses and the clients connected now (only if it is on)."""
    shared = snapshot.shared_bus
    if not shared.enabled:
        return {}
    clients = {
        name: sorted(dict(client.peers)) for name, client in sorted(dict(shared.clients).items())
    }
    return {"shared_bus": {"listening": list(shared.listening), "clients": clients}}


# --- the HTTP server -------------------------------------------------------------------------


class _Server(ThreadingHTTPServer):
    """The HTTP server with what its handlers read."""

    daemon_threads = True  # a hung scraper never holds up shutdown

    def __init__(
        self, address: tuple[str, int], *, state: GatewayState, registry: CollectorRegistry
    ) -> None:
        self.state = state
        self.registry = registry
        super().__init__(address, _Handler)

    def server_bind(self) -> None:
        # HTTPServer.server_bind looks the host's FQDN up (reverse DNS, slow or hanging
        # on a plant network); the name is never used here.
        socketserver.TCPServer.server_bind(self)
        host, port = self.server_address[:2]
        self.server_name = str(host)
        self.server_port = int(port)

    def handle_error(self, request: object, client_address: object) -> None:  # noqa: ARG002
        # Called in the except block of the request's thread. A scraper that hangs up
        # mid-answer is not worth the base's traceback on standard error.
        _LOGGER.debug("metrics request from %s failed: %r", client_address, sys.exc_info()[1])


class _Server6(_Server):
    address_family = socket.AF_INET6


class _Handler(BaseHTTPRequestHandler):
    """``GET /metrics``, ``/healthz``, ``/care``; ``POST /verify`` from this machine; else 404."""

    server: _Server
    server_version = "rs485-gateway"
    timeout = REQUEST_TIMEOUT_S  # a client that connects and says nothing is let go

    def do_GET(self) -> None:  # the name http.server dispatches to
        """Answer one request."""
        path = urlsplit(self.path).path
        try:
            status, content_type, body = self._answer(path)
        except Exception:  # a broken scrape must not end the thread silently: log, answer 500
            _LOGGER.exception("GET %s failed", path)
            status, content_type, body = _INTERNAL_ERROR
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(sum(len(piece) for piece in body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        for piece in body:
            self.wfile.write(piece)
        if path == "/metrics":
            del body
            release_free_memory()

    def do_POST(self) -> None:  # the name http.server dispatches to
        """``POST /verify`` from this machine: ``gateway verify`` asking the running gateway.

        Only from a loopback address: the metrics port is often open to the plant network
        for Prometheus, and a verification is a record. The body is one JSON object.
        """
        path = urlsplit(self.path).path
        status, answer = self._verification(path)
        body = json.dumps(answer).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _verification(self, path: str) -> tuple[int, dict[str, object]]:
        verify = self.server.state.writes.verify
        if path != "/verify" or verify is None:
            return HTTPStatus.NOT_FOUND, {"status": "error", "reason": f"{path} not found"}
        if not ipaddress.ip_address(self.client_address[0].split("%")[0]).is_loopback:
            _LOGGER.warning(
                "POST /verify refused from %s: not this machine", self.client_address[0]
            )
            return HTTPStatus.FORBIDDEN, {
                "status": "refused",
                "reason": "verifications come from this machine only (gateway verify)",
            }
        try:
            length = int(self.headers.get("Content-Length") or 0)
            if not 0 < length <= MAX_POST_BYTES:
                raise ValueError(f"a body of 1 to {MAX_POST_BYTES} bytes, not {length}")  # noqa: TRY301
            body = json.loads(self.rfile.read(length))
            if not isinstance(body, dict):
                raise ValueError("the body must be a JSON object")  # noqa: TRY004, TRY301
        except (ValueError, UnicodeDecodeError) as exc:
            return HTTPStatus.BAD_REQUEST, {"status": "refused", "reason": str(exc)}
        try:
            return verify(body)
        except Exception:  # the request's thread must answer: log, answer 500
            _LOGGER.exception("POST /verify failed")
            return HTTPStatus.INTERNAL_SERVER_ERROR, {"status": "error", "reason": "see the log"}

    def _answer(self, path: str) -> tuple[HTTPStatus, str, Sequence[bytes]]:
        """The status, content type and body (in pieces) of one request."""
        if path == "/metrics":
            return HTTPStatus.OK, CONTENT_TYPE_PLAIN_0_0_4, exposition(self.server.registry)
        if path == "/healthz":
            healthy, report = health_report(self.server.state)
            status = HTTPStatus.OK if healthy else HTTPStatus.SERVICE_UNAVAILABLE
            return status, "application/json", [json.dumps(report).encode()]
        if path == "/care":
            # Sensor care's documents, most urgent first: what `gateway care` shows.
            body = [report.as_dict() for report in care_order(self.server.state.care.reports())]
            return HTTPStatus.OK, "application/json", [json.dumps(body).encode()]
        text = f"{path} not found: GET /metrics, /healthz or /care\n"
        return HTTPStatus.NOT_FOUND, "text/plain; charset=utf-8", [text.encode()]

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 - the base's name
        """Requests go to the debug log, not to standard error."""
        _LOGGER.debug("%s %s", self.address_string(), format % args)


def _serve(server: _Server, stop: int) -> None:
    """Accept scrapes until a byte arrives on ``stop``: asleep in between.

    ``serve_forever`` wakes every ``poll_interval`` to look for a shutdown; at the 0.1 s
    that bounds a stop, those wakes took the GIL ten times a second from a gateway that
    polls once a second, a few per cent of its CPU.
    """
    with selectors.DefaultSelector() as selector:
        selector.register(server, selectors.EVENT_READ)
        selector.register(stop, selectors.EVENT_READ)
        while True:
            for key, _ in selector.select():
                if key.fileobj == stop:
                    return
                server.handle_request()  # one waiting connection, to a thread


class MetricsServer:
    """Serves ``/metrics`` and ``/healthz`` for a :class:`GatewayState` in its own thread.

    Example::

        server = MetricsServer(state, host="0.0.0.0", port=9108)
        server = MetricsServer.of(state, config.prometheus)  # where and what the config says
        server.start()  # PublishError if the port is taken
        ...
        server.stop()

    ``port=0`` binds a free port; :attr:`port` tells which.
    """

    def __init__(
        self,
        state: GatewayState,
        *,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        selection: Selection | None = None,
    ) -> None:
        """Serve ``state`` on ``host:port`` once started: the points ``selection`` selects."""
        self.state = state
        self.host = host
        self.registry = CollectorRegistry()
        self.collector = GatewayCollector(state, selection=selection)
        self.registry.register(self.collector)
        self._requested_port = port
        self._bound_port: int | None = None
        self._server: _Server | None = None
        self._thread: threading.Thread | None = None
        self._stop_pipe: tuple[int, int] | None = None  # read end, write end

    @classmethod
    def of(cls, state: GatewayState, settings: PrometheusConfig) -> MetricsServer:
        """The server a config's ``prometheus:`` section describes (``enabled`` aside)."""
        return cls(state, host=settings.host, port=settings.port, selection=Selection.of(settings))

    @property
    def port(self) -> int:
        """The port bound by the last start (the requested one before any)."""
        return self._requested_port if self._bound_port is None else self._bound_port

    def start(self) -> None:
        """Bind and serve in a daemon thread; a port in use raises :class:`PublishError`."""
        if self._server is not None:
            return
        server_class = _Server6 if ":" in self.host else _Server
        where = f"[{self.host}]" if ":" in self.host else self.host
        try:
            server = server_class(
                (self.host, self._requested_port), state=self.state, registry=self.registry
            )
        except OSError as exc:
            raise PublishError(
                f"cannot serve metrics on {where}:{self._requested_port}: "
                f"{exc.strerror or exc} (prometheus.host, prometheus.port)"
            ) from exc
        stop_pipe = os.pipe()
        thread = threading.Thread(
            target=_serve,
            args=(server, stop_pipe[0]),
            name=f"prometheus[{where}:{server.server_address[1]}]",
            daemon=True,
        )
        self._server, self._thread, self._stop_pipe = server, thread, stop_pipe
        self._bound_port = int(server.server_address[1])
        thread.start()
        _LOGGER.info("serving /metrics and /healthz on %s:%d", where, self.port)
        if self.collector.selection.legacy_names:
            _LOGGER.warning(
                "prometheus.legacy_names: the values are also exported under their old "
                "names, which the next release drops; move dashboards and alerts to the new "
                "names (the manual: Prometheus and Grafana, Migration) and remove legacy_names"
            )

    def stop(self) -> None:
        """Stop serving and close the socket (idempotent).

        Bounded: the serving loop wakes on a byte written to its stop pipe (it only accepts
        connections; each is handled in a daemon thread of its own), and the thread is
        joined for at most :data:`STOP_TIMEOUT_S`.
        """
        server, thread, stop_pipe = self._server, self._thread, self._stop_pipe
        self._server = self._thread = self._stop_pipe = None
        if server is None or stop_pipe is None:
            return
        os.write(stop_pipe[1], b"\0")
        if thread is not None:
            thread.join(STOP_TIMEOUT_S)
            if thread.is_alive():
                _LOGGER.warning("metrics server thread still running after %.1f s", STOP_TIMEOUT_S)
        server.server_close()
        for end in stop_pipe:
            os.close(end)

    def __enter__(self) -> Self:
        """Start serving."""
        self.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        """Stop serving."""
        self.stop()


def _records_head(snapshot: GatewayState) -> dict[str, object] | None:
    """The record store's head, as ``{base}/records/head`` publishes it."""
    head_of = snapshot.writes.records_head
    if head_of is None:
        return None
    head = head_of()
    return {"head": {"seq": head.seq, "hash": head.hash}}
