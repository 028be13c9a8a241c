"""MQTT commands in, results out: ``…/{point}/set`` and ``…/command/{name}``.

Topics under ``{base}``:

- ``{base}/{device}/{point}/set``: a plain value or ``{"value": …, "id": …}``; the outcome
  goes to ``{base}/{device}/{point}/set/result``;
- ``{base}/{device}/command/{name}``: an operation (``set_clock``, ``measure``,
  ``calibration_log``, ``calibrations``) with an empty payload or a JSON object of
  arguments and an ``id``;
  the outcome goes to ``{base}/{device}/command/{name}/result``.

Every outcome is one JSON object: ``status`` ``ok`` or ``error``, the echoed ``id``, and
either the value read back (``value``, ``written``) or the operation's ``result``, or the
``reason`` of an error. Rejections are logged as warnings too. Commands to one device run
one after another (a flash write's check and write must not interleave with another's);
commands to different devices, and polling, go on meanwhile.

A command the broker hands over as retained is refused: that happens when the gateway
subscribes (at every start and reconnection), so a command left retained would otherwise
be written again each time. (A retained command published while the gateway is connected
reaches it as a live message, as MQTT 3.1.1 section 3.3.1.3 requires, and is run once.)
"""

from __future__ import annotations

import asyncio
import json
import logging
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Final

from gateway.control.commands import parse_json, parse_set_payload
from gateway.control.verification import VerificationRequest
from gateway.errors import CommandRejectedError, GatewayError
from gateway.line.samples import json_value
from gateway.publish.message import Message
from gateway.records.actor import Actor, Via, acting, current

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping

    from gateway.control.verification import Verifier
    from gateway.control.writes import SafeWriter
    from gateway.shared.state import GatewayState

_LOGGER = logging.getLogger(__name__)

COMMAND_TIMEOUT_S: Final = 60.0  # a set or a measurement; a stuck bus answers within it
SET: Final = "set"
COMMAND: Final = "command"
RESULT: Final = "result"


@dataclass(frozen=True, slots=True)
class Route:
    """What a command topic names: a point to set, or an operation to run."""

    kind: str  # SET or COMMAND
    device: str
    name: str  # the point, or the operation


VERIFY: Final = "verify"  # a grab-sample verification: recorded, nothing written


def parse_topic(base: str, topic: str) -> Route | None:
    """The command a topic carries, or ``None`` for any other topic (results included)."""
    prefix = f"{base}/"
    if not topic.startswith(prefix):
        return None
    parts = topic[len(prefix) :].split("/")
    if len(parts) != 3 or not all(parts):  # noqa: PLR2004 - device, point|command, set|name
        return None
    device, middle, last = parts
    if middle == COMMAND:
        return Route(COMMAND, device, last)
    if last == SET:
        return Route(SET, device, middle)
    return None


def _parse_arguments(payload: bytes) -> tuple[dict[str, object], str | None]:
    """An operation's arguments and id: an empty payload, or a JSON object."""
    try:
        text = payload.decode("utf-8").strip()
    except UnicodeDecodeError as exc:
        raise CommandRejectedError(f"the payload is not UTF-8 text: {exc}") from exc
    if not text:
        return {}, None
    data = parse_json(text)
    if not isinstance(data, dict):
        raise CommandRejectedError("the payload must be empty or a JSON object of arguments")
    raw_id = data.pop("id", None)
    if raw_id is not None and not isinstance(raw_id, str | int | float):
        raise CommandRejectedError(f"the id must be a JSON string or number, got {raw_id!r}")
    command_id = raw_id if isinstance(raw_id, str) or raw_id is None else json.dumps(raw_id)
    return data, command_id


def _salvage_id(payload: bytes) -> str | None:
    """The id of a payload that was refused, if one can be read, to echo it anyway."""
    try:
        data = parse_json(payload.decode("utf-8"))
    except (UnicodeDecodeError, CommandRejectedError):
        return None
    raw = data.get("id") if isinstance(data, dict) else None
    if isinstance(raw, str):
        return raw
    return json.dumps(raw) if isinstance(raw, int | float) else None


class CommandRouter:
    """Turns command messages into writes and operations, and their outcomes into results."""

    def __init__(
        self,
        base: str,
        writers: Mapping[str, SafeWriter],
        *,
        state: GatewayState | None = None,
        qos: int = 1,
        timeout_s: float = COMMAND_TIMEOUT_S,
        clock: Callable[[], datetime] = lambda: datetime.now(UTC),
        actor: Actor | None = None,
        verifier: Verifier | None = None,
    ) -> None:
        """Route commands under ``base`` to the writers of the configured devices.

        ``actor``: who the records name for a command (the broker connection's username
        and client id: MQTT does not tell a subscriber who published). ``verifier``: where
        ``…/command/verify`` (a grab-sample verification) goes.
        """
        self.verifier = verifier
        self.base = base
        self.actor = actor or Actor(user="mqtt", via=Via.MQTT)
        self.writers = dict(writers)
        self.state = state
        self.qos = qos
        self.timeout_s = timeout_s
        self._clock = clock
        self._locks = {name: asyncio.Lock() for name in self.writers}

    def subscriptions(self) -> list[str]:
        """The topic filters to subscribe to."""
        return [f"{self.base}/+/+/{SET}", f"{self.base}/+/{COMMAND}/+"]

    async def handle(self, topic: str, payload: bytes, *, retained: bool = False) -> list[Message]:
        """Run one command message; the result message to publish (none for other topics)."""
        route = parse_topic(self.base, topic)
        if route is None:
            return []
        started = self._clock()
        try:
            writer = self._writer_for(route, retained=retained)
            actor = replace(self.actor, detail=_joined(self.actor.detail, f"topic {topic}"))
            async with self._locks[route.device], asyncio.timeout(self.timeout_s):
                with acting(actor):
                    body, outcome = await self._run(route, payload, writer)
        except CommandRejectedError as exc:
            body = {"status": "error", "id": _salvage_id(payload), "reason": str(exc)}
            outcome = "rejected"
            _LOGGER.warning("command %s refused: %s", topic, exc)
        except TimeoutError:
            body = {
                "status": "error",
                "id": _salvage_id(payload),
                "reason": (
                    f"no outcome within {self.timeout_s:g} s (the device does not answer or "
                    "its port is down); a write may still have reached it"
                ),
            }
            outcome = "failed"
            _LOGGER.warning("command %s: %s", topic, body["reason"])
        except GatewayError as exc:
            body = {"status": "error", "id": _salvage_id(payload), "reason": str(exc)}
            outcome = "failed"
            _LOGGER.warning("command %s failed: %s", topic, exc)
        if self.state is not None:
            device = route.device if route.device in self.writers else "unknown"
            self.state.count_write(device, route.kind, outcome)
        body |= {"device": route.device, route_key(route): route.name}
        body["time"] = started.isoformat()
        return [
            Message.text(f"{topic}/{RESULT}", json.dumps(body, ensure_ascii=False), qos=self.qos)
        ]

    def _writer_for(self, route: Route, *, retained: bool) -> SafeWriter:
        if retained:
            raise CommandRejectedError(
                "a retained command, delivered again at (re)connection, is refused: it would "
                "be written at every reconnection; publish commands without the retain flag "
                "and clear this one (an empty retained message on its topic)"
            )
        writer = self.writers.get(route.device)
        if writer is None:
            known = ", ".join(sorted(self.writers)) or "none"
            raise CommandRejectedError(f"no device {route.device!r} (devices: {known})")
        return writer

    async def _run(
        self, route: Route, payload: bytes, writer: SafeWriter
    ) -> tuple[dict[str, object], str]:
        if route.kind == SET:
            command = parse_set_payload(payload)
            try:
                with acting(current().because(command.reason)):
                    done = await writer.set(writer.point(route.name), command.value)
            except CommandRejectedError:
                raise  # refused before anything was sent
            except GatewayError as exc:
                _LOGGER.warning("set %s/%s failed: %s", route.device, route.name, exc)
                return {"status": "error", "id": command.id, "reason": str(exc)}, "failed"
            body: dict[str, object] = {
                "status": "ok",
                "id": command.id,
                "value": json_value(done.value),  # type: ignore[arg-type]
                "written": done.written,
            }
            if done.note:
                body["note"] = done.note
            _LOGGER.info(
                "set %s/%s = %r: %s",
                route.device,
                route.name,
                command.value,
                "written" if done.written else done.note,
            )
            return body, "ok" if done.written else "unchanged"
        arguments, command_id = _parse_arguments(payload)
        if route.name == VERIFY and self.verifier is not None:
            request = VerificationRequest.from_arguments(arguments)
            with acting(current().because(request.reason)):
                verified = await self.verifier.verify(route.device, request)
            _LOGGER.info(
                "verification of %s: %s (record %d)",
                route.device,
                "passed" if verified.judgement.passed else "failed",
                verified.record.seq,
            )
            return {"status": "ok", "id": command_id, "result": verified.as_dict()}, "ok"
        reason = arguments.pop("reason", "")
        if not isinstance(reason, str):
            raise CommandRejectedError(f"the reason must be a JSON string, got {reason!r}")
        # The operations (clock, measurement, calibration log and offers) are imported
        # with the first one asked: a plant that never asks keeps none of their code.
        from gateway.control import operations  # noqa: PLC0415

        try:
            with acting(current().because(reason.strip())):
                result = await operations.run_operation(
                    route.name, writer, arguments, now=self._clock()
                )
        except CommandRejectedError:
            raise  # refused before anything was sent
        except GatewayError as exc:
            return {"status": "error", "id": command_id, "reason": str(exc)}, "failed"
        _LOGGER.info("command %s on %s done", route.name, route.device)
        return {"status": "ok", "id": command_id, "result": result}, "ok"


def _joined(*parts: str) -> str:
    return "; ".join(part for part in parts if part)


def route_key(route: Route) -> str:
    """The result's key naming what was commanded: ``point`` or ``command``."""
    return "point" if route.kind == SET else "command"
