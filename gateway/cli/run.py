"""``gateway run``: the gateway until Ctrl-C or SIGTERM, and a plain run read without typer.

A running gateway keeps whatever it imported for as long as it runs, months in a cabinet,
and the command line's libraries (typer with its click, and rich) were 3.7 MiB of it
(``bench/memory.py --reference``) for the millisecond they take to read ``run --config
FILE``. So the entry point reads that command line itself when it is exactly a plain run:
``run``, then only ``--config FILE``, ``-c FILE`` or ``--config=FILE`` and ``--print`` or
``--no-print``, read as typer reads them (the last of a repeated option wins). Anything
else (help, another command, a mistake, a shell's completion) goes to the typer app,
which reads it and answers as for every command. A plain run ends as typer would end it
too: the same exit codes, and an error printed by the command line's own ``fail``, which
imports rich then (what is printed on the way out costs no memory kept).
"""

from __future__ import annotations

import asyncio
import errno
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Final

from gateway.app import configure_logging
from gateway.app import run as run_gateway
from gateway.cli.heap import one_arena, return_large_blocks
from gateway.config import load_config
from gateway.errors import GatewayError
from gateway.publish.console import ConsoleSink

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

CONFIG_OPTIONS: Final = frozenset({"--config", "-c"})
PRINT_OPTIONS: Final = {"--print": True, "--no-print": False}
INTERRUPTED: Final = 130  # typer's exit code for Ctrl-C outside the gateway's own handling


def plain_run(args: Sequence[str], environ: Mapping[str, str]) -> tuple[Path, bool | None] | None:
    """The config and ``--print`` choice of a plain ``run`` command line; ``None`` otherwise.

    ``None`` for whatever typer should read: another command, help, an option this does
    not know, an option value it might read otherwise (empty, or starting with ``-``),
    a missing ``--config``, and a shell asking for completions (``_GATEWAY_COMPLETE``
    or the like in the environment).
    """
    if not args or args[0] != "run":
        return None
    if any(name.startswith("_") and name.endswith("_COMPLETE") for name in environ):
        return None
    config: str | None = None
    show: bool | None = None
    rest = list(args[1:])
    while rest:
        arg = rest.pop(0)
        if arg in PRINT_OPTIONS:
            show = PRINT_OPTIONS[arg]
        elif arg in CONFIG_OPTIONS and rest and not rest[0].startswith("-") and rest[0]:
            config = rest.pop(0)
        elif arg.startswith("--config=") and len(arg) > len("--config="):
            config = arg.removeprefix("--config=")
        else:
            return None
    return (Path(config), show) if config is not None else None


def run_command(config: Path, *, show: bool | None) -> None:
    """Poll every configured bus and publish until Ctrl-C or SIGTERM (typer's ``run`` too).

    A config or start-up error is raised as the ``GatewayError`` it is, for the caller to
    print as the command line prints every error.
    """
    settings = load_config(config)
    configure_logging(settings.logging)
    return_large_blocks()
    one_arena()
    console = show if show is not None else sys.stdout.isatty()
    asyncio.run(run_gateway(settings, [ConsoleSink()] if console else [], config_path=config))


def main_plain(config: Path, *, show: bool | None) -> None:
    """A plain run from the entry point, ended as typer's standalone mode ends a command."""
    try:
        run_command(config, show=show)
    except GatewayError as exc:
        # Imported on the way out only: the command line's one way of printing an error.
        from gateway.cli.device import fail  # noqa: PLC0415

        raise SystemExit(fail(exc).exit_code) from exc
    except KeyboardInterrupt:
        raise SystemExit(INTERRUPTED) from None
    except OSError as exc:
        if exc.errno != errno.EPIPE:
            raise
        # What typer does on a closed pipe: no second error while flushing at exit.
        from typer._click.utils import PacifyFlushWrapper  # noqa: PLC0415

        sys.stdout = PacifyFlushWrapper(sys.stdout)
        sys.stderr = PacifyFlushWrapper(sys.stderr)
        raise SystemExit(1) from None
