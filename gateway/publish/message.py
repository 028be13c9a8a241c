"""One MQTT message as the gateway queues it: built by the sink, stored, then sent."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True, kw_only=True)
class Message:
    """Topic, payload and delivery options of one MQTT publish."""

    topic: str
    payload: bytes
    qos: int = 1
    retain: bool = False

    @classmethod
    def text(cls, topic: str, payload: str, *, qos: int = 1, retain: bool = False) -> Message:
        """A message with a UTF-8 text payload."""
        return cls(topic=topic, payload=payload.encode(), qos=qos, retain=retain)
