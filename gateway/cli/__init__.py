"""The ``gateway`` command line: one entry point with sub-commands."""

from gateway.cli.root import main

__all__ = ["main"]
