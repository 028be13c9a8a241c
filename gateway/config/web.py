"""The ``web:`` section: the commissioning and calibration page, and who may sign in."""

from __future__ import annotations

import re
from pathlib import Path  # noqa: TC003 - pydantic resolves annotations at run time
from typing import Annotated

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, SecretStr

from gateway.config.fields import TcpPort  # noqa: TC001 - pydantic resolves it at run time


class _Model(BaseModel):
    # The same as config.model's: declared here, on BaseModel, so ruff still sees pydantic
    # models, whose list defaults are copied per instance.
    model_config = ConfigDict(extra="forbid", frozen=True)


def _sha256_hex(value: str | None) -> str | None:
    if value is not None and not re.fullmatch(r"[0-9a-fA-F]{64}", value):
        raise ValueError("expected a SHA-256 digest as 64 hexadecimal digits")
    return value.lower() if value is not None else None


_HOST_LABEL = r"(?!-)[a-z0-9-]{1,63}(?<!-)"
_HOST_NAME = re.compile(rf"(?:\*\.)?{_HOST_LABEL}(?:\.{_HOST_LABEL})*\.?")


def _host_name(value: str) -> str:
    """A host name (or ``*.`` and a domain) as the page's ``Host`` header may carry it."""
    name = value.strip().lower()
    if "://" in name or "/" in name:
        raise ValueError(f"{value!r}: a host name only, without scheme or path")
    if name.count(":") == 1 or (name.startswith("[") and "]:" in name):
        raise ValueError(f"{value!r}: a host name only, without a port")
    if name.startswith("[") and name.endswith("]"):
        name = name[1:-1]
    if ":" in name or re.fullmatch(r"[0-9.]+", name):
        return name  # an address: checked as one by the page
    if not _HOST_NAME.fullmatch(name):
        raise ValueError(f"{value!r} is not a host name (letters, digits, '-' and '.')")
    return name.rstrip(".")


class WebConfig(_Model):
    """The commissioning and calibration page in the browser (off unless enabled).

    Reading is open to this machine only (loopback); from elsewhere, and for any write or
    calibration, the page asks the user to sign in: by name, as one of the users of the
    users file (``gateway users add NAME --role operator``; ``users_file``, by default
    ``users.json`` in ``state_dir``), or with the one shared password of a plant without
    accounts, meant to come from the environment (``GATEWAY_WEB__PASSWORD``). Without
    users and a password, the page is read-only. Example::

        web: {enabled: true, port: 8080}  # http://127.0.0.1:8080/
        web: {enabled: true, host: 0.0.0.0, allowed_hosts: [gateway.plant.example]}
        web: {enabled: true, users_file: /etc/rs485-gateway/users.json}
    """

    enabled: bool = False
    host: Annotated[str, Field(min_length=1)] = "127.0.0.1"
    port: TcpPort = 8080
    password: SecretStr | None = None
    # The shared password as its SHA-256, for configs written before the users file: a
    # fast hash, kept only for compatibility (a stolen config gives a guesser billions of
    # tries a second). The gateway keeps it as a scrypt hash in memory; named users in
    # the users file (slow salted hashes, a name on every record) are the way to go.
    password_sha256: Annotated[str | None, AfterValidator(_sha256_hex)] = None
    # The page's named users and their roles (``gateway users``); None: users.json in
    # state_dir. A file that does not exist means no named users.
    users_file: Path | None = None
    session_minutes: Annotated[float, Field(gt=0, le=24 * 60)] = 30.0
    # The names the page answers to in ``Host`` (besides the listen address, and localhost
    # from this machine): a name not listed is a DNS-rebinding attempt, refused with 421.
    allowed_hosts: list[Annotated[str, AfterValidator(_host_name)]] = []
    # A calibration waiting for the operator's "write" ends after this, nothing written.
    confirm_minutes: Annotated[float, Field(gt=0, le=60)] = 10.0
