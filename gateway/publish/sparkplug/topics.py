"""Sparkplug B topics, without I/O: ``spBv1.0/{group}/{type}/{edge node}[/{device}]``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

NAMESPACE: Final = "spBv1.0"  # Sparkplug 3.0, 4.1.1


@dataclass(frozen=True, slots=True)
class SparkplugTopics:
    """The topics of one edge node in one group, and of its primary host's STATE."""

    group: str
    edge: str
    host: str | None = None

    def _node(self, kind: str) -> str:
        return f"{NAMESPACE}/{self.group}/{kind}/{self.edge}"

    @property
    def nbirth(self) -> str:
        """The node's birth certificate."""
        return self._node("NBIRTH")

    @property
    def ndeath(self) -> str:
        """The node's death certificate (its last will)."""
        return self._node("NDEATH")

    @property
    def ncmd(self) -> str:
        """Commands to the node (Node Control/Rebirth)."""
        return self._node("NCMD")

    @property
    def dcmd_filter(self) -> str:
        """Commands to any of its devices."""
        return f"{self._node('DCMD')}/+"

    @property
    def state(self) -> str | None:
        """The primary host's STATE (Sparkplug 3.0: ``spBv1.0/STATE/{host}``)."""
        return None if self.host is None else f"{NAMESPACE}/STATE/{self.host}"

    def device(self, kind: str, device: str) -> str:
        """``DBIRTH``, ``DDATA`` or ``DDEATH`` of one device."""
        return f"{self._node(kind)}/{device}"

    def device_of(self, topic: str) -> str | None:
        """The device a DCMD topic names, or ``None`` for any other topic."""
        prefix = f"{self._node('DCMD')}/"
        if not topic.startswith(prefix):
            return None
        device = topic[len(prefix) :]
        return device if device and "/" not in device else None

    def device_of_data(self, topic: str) -> str | None:
        """The device of a DDATA topic (what the store holds), or ``None``."""
        prefix = f"{self._node('DDATA')}/"
        return topic[len(prefix) :] if topic.startswith(prefix) else None
