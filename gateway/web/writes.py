"""The page's writes and whole-map reads: a point set through its device's SafeWriter.

Each write runs under the session user's :class:`~gateway.records.actor.Actor`, so its
records name who did it, from where and why; it is counted by outcome (ok, rejected,
failed) as MQTT's and the CLI's are.
"""

from __future__ import annotations

import json
import logging
import time
from typing import TYPE_CHECKING

from aiohttp import web

from gateway.errors import CommandRejectedError, ConfigError, GatewayError, ProfileError
from gateway.line.samples import json_value
from gateway.records.actor import acting
from gateway.web.guards import SESSION, error, json_body, reason, who
from gateway.web.live import sample_view

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.control.writes import SafeWriter
    from gateway.shared.state import GatewayState
    from gateway.web.guards import Guards

_LOGGER = logging.getLogger(__name__)


class WriteRoutes:
    """``POST /api/devices/{device}/points/{point}`` and ``/read``, behind the write guard."""

    def __init__(
        self, writers: Mapping[str, SafeWriter], state: GatewayState, guards: Guards
    ) -> None:
        """Write through ``writers`` (by device name), count on ``state``, sign by ``guards``."""
        self.writers = writers
        self.state = state
        self.guards = guards

    async def read_all(self, request: web.Request) -> web.StreamResponse:
        """Every point of the device read now, for the register map; nothing is published.

        A session is asked for: a read of a whole map takes the line for a while.
        """
        device = request.match_info["device"]
        writer = self.writers.get(device)
        if writer is None:
            return error(404, f"no device {device!r}")
        points = [point for point in writer.link.profile.points if not point.view]
        _LOGGER.info("web: %s reads every point of %s", who(request), device)
        try:
            samples = await writer.link.worker.read_points(device, points)
        except GatewayError as exc:
            return error(502, str(exc))
        now = time.monotonic()
        return web.json_response(
            {"values": [sample_view(s, stale=False, now=now) for s in samples]}
        )

    # --- writing ----------------------------------------------------------------------

    async def write(self, request: web.Request) -> web.StreamResponse:
        """One point written through its device's SafeWriter, signed if a password is given."""
        device = request.match_info["device"]
        writer = self.writers.get(device)
        if writer is None:
            return error(404, f"no device {device!r}")
        by = who(request)
        try:
            body = await json_body(request)
            signed = await self.guards.signature(request, body, what="the write", required=False)
            if isinstance(signed, web.Response):
                return signed
            actor = request[SESSION].actor(str(request.remote), reason=reason(body), signed=signed)
            value = body.get("value")
            if isinstance(value, str) and value.lstrip().startswith("{"):
                value = json.loads(value)
            point = writer.point(request.match_info["point"])
            _LOGGER.info("web: %s writes %s/%s = %r", by, device, point.name, value)
            with acting(actor):  # the records of this write name the session's user
                outcome = await writer.set(point, value)
        except (CommandRejectedError, ConfigError, ProfileError, ValueError) as exc:
            _LOGGER.warning("web: write by %s to %s refused: %s", by, device, exc)
            self.state.count_write(device, "web", "rejected")
            return error(400, str(exc))
        except GatewayError as exc:
            _LOGGER.warning("web: write by %s to %s failed: %s", by, device, exc)
            self.state.count_write(device, "web", "failed")
            return error(502, str(exc))
        self.state.count_write(device, "web", "ok")
        _LOGGER.info(
            "web: %s wrote %s/%s: %s, the device holds %r",
            by,
            device,
            outcome.point,
            "written" if outcome.written else "unchanged",
            outcome.value,
        )
        return web.json_response(
            {
                "device": device,
                "point": outcome.point,
                "written": outcome.written,
                "value": json_value(outcome.value),  # type: ignore[arg-type]
                "registers": list(outcome.registers),
                "flash": outcome.flash,
                "note": outcome.note,
            }
        )
