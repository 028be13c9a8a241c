"""``gateway reload``: check the config, have the running gateway apply it, say how it went.

The file is checked here first, as ``check-config`` does. This command then hands its
``GATEWAY_*`` environment to the gateway, sends it SIGHUP (found by ``--pid``, else by the
PID file in its state directory) and waits for the outcome the gateway writes there
(:mod:`gateway.app.reload`): exit 0 applied, 1 not applied or no answer. A file with a
problem is signalled too, so that the running gateway says so where it is watched (its log,
``gateway_config_last_reload_successful`` 0) while it keeps its config; this command then
exits 2 with the problems. systemd's ``systemctl reload`` runs it as the unit's
``ExecReload``, so what it says goes to the journal: as JSON lines where the gateway logs
JSON (``logging.format``, or ``GATEWAY_LOGGING__FORMAT`` when the file cannot be read).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import time
from pathlib import Path
from typing import Annotated, Final, NoReturn

import typer
import yaml

from gateway.app import configure_logging, state_directory
from gateway.app.reload import PID_FILE, STATUS_FILE, hand_environment
from gateway.config import ConfigProblems, LoggingConfig, load_config
from gateway.errors import GatewayError

DEFAULT_CONFIG: Final = Path("/etc/rs485-gateway/gateway.yaml")  # deploy/systemd's
WAIT_S: Final = 30.0  # a reload that changes every bus waits for each to stop (5 s at most)
_LOGGER = logging.getLogger(__name__)


def reload(
    config: Annotated[
        Path, typer.Option("--config", "-c", help="The gateway's YAML config.")
    ] = DEFAULT_CONFIG,
    pid: Annotated[
        int | None,
        typer.Option(help="The running gateway's process id (default: its PID file)."),
    ] = None,
) -> None:
    """Apply an edited config to the running gateway without a restart.

    Checks the file first; the gateway then applies only what changed (a bus whose
    settings and devices are the same keeps polling) and keeps its running config if
    the file has a problem.
    """
    try:
        settings = load_config(config)
    except GatewayError as exc:
        _refuse(config, exc, pid)
    _log_like_the_gateway(settings.logging)
    state_dir = state_directory(settings)
    target = pid if pid is not None else _pid_file_of(state_dir)
    if target is None:
        _LOGGER.error(
            "no running gateway found: %s is missing or unreadable (is the service running, "
            "with this config's state_dir?); give its process id with --pid",
            state_dir / PID_FILE,
        )
        raise typer.Exit(code=1)
    before = _reloads_told(state_dir)
    _signal(target, state_dir)
    _wait_for_outcome(state_dir, before)


def _refuse(config: Path, exc: GatewayError, pid: int | None) -> NoReturn:
    """The file has problems: said here and, signalled, by the gateway, which keeps its config."""
    _log_like_the_gateway(None)
    problems = exc.problems if isinstance(exc, ConfigProblems) else [exc]
    for problem in problems:
        _LOGGER.error("%s: %s", config, problem)
    _LOGGER.error("%s: not reloaded: the running gateway keeps its config", config)
    state_dir = _state_dir_of_broken(config)
    target = pid if pid is not None else _pid_file_of(state_dir)
    if target is not None:
        _signal(target, state_dir)  # the gateway says so in its log and metrics
    raise typer.Exit(code=2)


def _state_dir_of_broken(config: Path) -> Path:
    """The state directory a file with problems names, if its ``state_dir`` can be read."""
    try:
        data = yaml.safe_load(config.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        data = None
    named = data.get("state_dir") if isinstance(data, dict) else None
    return Path(named) if isinstance(named, str) and named else state_directory(None)


def _log_like_the_gateway(settings: LoggingConfig | None) -> None:
    """This command's messages in the gateway's log format (the journal gets both)."""
    if settings is None:
        wanted = os.environ.get("GATEWAY_LOGGING__FORMAT", "text").lower()
        settings = LoggingConfig(format="json" if wanted == "json" else "text")
    configure_logging(settings)


def _pid_file_of(state_dir: Path) -> int | None:
    try:
        return int((state_dir / PID_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _signal(target: int, state_dir: Path) -> None:
    """Hand this command's environment over and send SIGHUP; a failure ends the command."""
    try:
        hand_environment(state_dir, os.environ)
    except OSError as exc:
        _LOGGER.warning(
            "cannot hand the environment over in %s (%s): the gateway keeps its own", state_dir, exc
        )
    try:
        os.kill(target, signal.SIGHUP)
    except ProcessLookupError:
        _LOGGER.error("no gateway runs as process %d (a stale %s?)", target, state_dir / PID_FILE)  # noqa: TRY400
        raise typer.Exit(code=1) from None
    except PermissionError:
        _LOGGER.error(  # noqa: TRY400 - the remedy is the message
            "not permitted to signal process %d: run as its user or root "
            "(`sudo systemctl reload rs485-gateway`)",
            target,
        )
        raise typer.Exit(code=1) from None


def _reloads_told(state_dir: Path) -> int:
    """How many reloads the gateway has told of so far (0: none, or no status file)."""
    try:
        return int(json.loads((state_dir / STATUS_FILE).read_text(encoding="utf-8"))["reloads"])
    except (OSError, ValueError, KeyError, TypeError):
        return 0


def _wait_for_outcome(state_dir: Path, before: int) -> None:
    deadline = time.monotonic() + WAIT_S
    path = state_dir / STATUS_FILE
    while time.monotonic() < deadline:
        time.sleep(0.1)
        try:
            document = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if int(document.get("reloads", 0)) <= before:
            continue
        if document.get("ok"):
            _LOGGER.info("reloaded: the running gateway applied the config")
            return
        for problem in document.get("problems", []):
            _LOGGER.error("not applied: %s", problem)
        raise typer.Exit(code=1)
    _LOGGER.error(
        "sent SIGHUP, but the gateway told no outcome within %.0f s in %s; see its log",
        WAIT_S,
        path,
    )
    raise typer.Exit(code=1)


def register(app: typer.Typer) -> None:
    """Add ``reload`` to the ``gateway`` command line."""
    app.command("reload")(reload)
