"""Operations on one sensor from the command line: clock, single measurement, logbook."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import typer


def register(app: typer.Typer) -> None:
    """Add this module's commands to the ``gateway`` command line."""
    del app
