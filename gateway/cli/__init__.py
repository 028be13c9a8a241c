"""The ``gateway`` command line: one entry point with sub-commands."""

import os
import sys

from gateway.cli.run import main_plain, plain_run

__all__ = ["main"]


def main() -> None:
    """Run the command line: a plain ``gateway run`` without typer, the rest with it.

    A plain run keeps no library it does not use (``cli/run`` says why and what counts as
    plain); every other command line, help included, is typer's (``cli/root``).
    """
    plain = plain_run(sys.argv[1:], os.environ)
    if plain is not None:
        config, show = plain
        main_plain(config, show=show)
        return
    from gateway.cli.root import app  # noqa: PLC0415 - typer and rich: not for a plain run

    app()
