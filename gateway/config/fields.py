"""The field types several sections of the config share: seconds, TCP ports, topics."""

from __future__ import annotations

from typing import Annotated, Final

from pydantic import AfterValidator, Field

MAX_INTERVAL_S: Final = 86_400.0  # a day; longer is a typo, not a polling plan


def mqtt_topic(value: str) -> str:
    """A base topic or prefix: no wildcards, no leading or trailing ``/``."""
    if not value or value.startswith("/") or value.endswith("/") or {"+", "#"} & set(value):
        raise ValueError(
            f"{value!r} is not a base topic: no wildcards (+, #) and no leading or trailing '/'"
        )
    return value


Seconds = Annotated[float, Field(gt=0, le=MAX_INTERVAL_S)]
TcpPort = Annotated[int, Field(ge=1, le=65535)]
BaseTopic = Annotated[str, AfterValidator(mqtt_topic)]
