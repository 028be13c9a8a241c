"""Reloading the config while the gateway runs: asked for, validated, applied, told.

A reload is asked for with SIGHUP: by ``kill -HUP``, by systemd's ``systemctl reload``
(the unit's ``ExecReload`` runs ``gateway reload``), or by ``gateway reload`` itself, which
finds the running gateway by the PID file it keeps in its state directory. The file is read
and validated first, exactly as ``check-config`` does: a file with problems is not applied,
the running config stays, the log names every problem with its key path and line, and
:class:`~gateway.shared.state.ConfigStatus` says so (``/healthz`` and the metrics
``gateway_config_last_reload_successful`` and ``…_success_timestamp_seconds``, the names
Prometheus uses for its own). A valid file is applied by
:meth:`~gateway.app.running.RunningGateway.reload`, which changes only what differs.

The environment is the reloading command's: ``gateway reload`` hands its ``GATEWAY_*``
variables over in a file of the state directory (readable by its owner only), so that
``systemctl reload`` applies an edited ``EnvironmentFile`` too, which systemd reads for
``ExecReload`` but cannot give the running process. A plain SIGHUP keeps the process's own.

The outcome is written to ``reload-status.json`` in the state directory for
``gateway reload`` to wait for and print.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import time
from typing import TYPE_CHECKING, Final

from gateway.config import ENV_PREFIX

if TYPE_CHECKING:
    from collections.abc import Mapping
    from pathlib import Path


_LOGGER = logging.getLogger(__name__)

PID_FILE: Final = "gateway.pid"
STATUS_FILE: Final = "reload-status.json"
ENVIRONMENT_FILE: Final = "reload-environment.json"  # gateway reload's GATEWAY_* variables


class ReloadRequests:
    """Reloads asked for and not yet begun: any number asked during one make one more after it."""

    def __init__(self) -> None:
        """None asked for yet."""
        self._asked = asyncio.Event()

    def ask(self) -> None:
        """A reload is wanted (a signal handler calls this)."""
        self._asked.set()

    async def next(self) -> None:
        """Wait for a reload to be asked for; the ones asked from now on make another."""
        await self._asked.wait()
        self._asked.clear()


def handed_environment(state_dir: Path) -> dict[str, str] | None:
    """The ``GATEWAY_*`` variables ``gateway reload`` handed over, once; None: none handed."""
    path = state_dir / ENVIRONMENT_FILE
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    finally:
        with contextlib.suppress(OSError):
            path.unlink()
    handed = json.loads(text)
    return {str(k): str(v) for k, v in handed.items() if str(k).startswith(ENV_PREFIX)}


def hand_environment(state_dir: Path, environ: Mapping[str, str]) -> None:
    """Hand this process's ``GATEWAY_*`` variables to the running gateway's next reload."""
    handed = {k: v for k, v in environ.items() if k.startswith(ENV_PREFIX)}
    path = state_dir / ENVIRONMENT_FILE
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)  # secrets may be in it
    with os.fdopen(fd, "w", encoding="utf-8") as out:
        json.dump(handed, out)


def reload_environment(state_dir: Path) -> dict[str, str]:
    """The environment a reload reads the config with: the process's, ``GATEWAY_*`` handed over."""
    handed = handed_environment(state_dir)
    if handed is None:
        return dict(os.environ)
    keep = {k: v for k, v in os.environ.items() if not k.startswith(ENV_PREFIX)}
    return {**keep, **handed}


def write_status(state_dir: Path, reloads: int, ok: bool, problems: tuple[str, ...]) -> None:  # noqa: FBT001
    """The last reload's outcome, for ``gateway reload`` (a failure to write is only logged)."""
    document = {"reloads": reloads, "ok": ok, "problems": list(problems), "at": time.time()}
    try:
        (state_dir / STATUS_FILE).write_text(json.dumps(document), encoding="utf-8")
    except OSError as exc:
        _LOGGER.warning("reload: cannot write %s: %s", state_dir / STATUS_FILE, exc)


def write_pid_file(state_dir: Path) -> Path | None:
    """This process's PID in the state directory, for ``gateway reload`` to find it."""
    path = state_dir / PID_FILE
    try:
        state_dir.mkdir(parents=True, exist_ok=True)
        path.write_text(f"{os.getpid()}\n", encoding="utf-8")
    except OSError as exc:
        _LOGGER.warning("cannot write %s (%s): `gateway reload` will need --pid", path, exc)
        return None
    return path


def remove_pid_file(path: Path | None) -> None:
    """At the stop: the PID file goes, if it is still this process's."""
    if path is None:
        return
    with contextlib.suppress(OSError, ValueError):
        if int(path.read_text(encoding="utf-8")) == os.getpid():
            path.unlink()
