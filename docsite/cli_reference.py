"""The command reference: ``gateway --help`` and every command's help, as the commands say it.

Each help is the command line's own text, asked for in this process (typer's test runner at
a fixed width, without colour), so the page says what ``gateway COMMAND --help`` says.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

import typer
from typer.core import TyperGroup
from typer.testing import CliRunner

from gateway.cli.root import app

if TYPE_CHECKING:
    from collections.abc import Iterator

PAGE: Final = "reference/cli.md"
WIDTH: Final = 100


def commands(
    group: TyperGroup | None = None, prefix: tuple[str, ...] = ()
) -> Iterator[tuple[str, ...]]:
    """Every command's words (``("profiles", "show")``), depth first, in the help's order."""
    if group is None:
        group = typer.main.get_group(app)
    context = group.context_class(group, info_name="gateway")
    for name in group.list_commands(context):
        command = group.get_command(context, name)
        if command is None or command.hidden:
            continue
        yield (*prefix, name)
        if isinstance(command, TyperGroup):
            yield from commands(command, (*prefix, name))


def help_text(words: tuple[str, ...]) -> str:
    """What ``gateway WORDS --help`` prints."""
    result = CliRunner().invoke(
        app,
        [*words, "--help"],
        env={"COLUMNS": str(WIDTH), "NO_COLOR": "1", "TERM": "dumb"},
        terminal_width=WIDTH,
        color=False,
    )
    if result.exit_code != 0:
        raise RuntimeError(f"gateway {' '.join(words)} --help failed: {result.output}")
    return "\n".join(line.rstrip() for line in result.output.strip("\n").splitlines())


def page() -> str:
    """The reference as a Markdown page."""
    lines = [
        "# Command reference",
        "",
        "Each command's help, as `gateway COMMAND --help` prints it (made when this site was",
        "built). The [command line](../configuration/cli.md) page says what each command is for,",
        "with examples.",
        "",
        "## gateway",
        "",
        "```text",
        help_text(()),
        "```",
    ]
    for words in commands():
        lines += ["", f"## gateway {' '.join(words)}", "", "```text", help_text(words), "```"]
    return "\n".join(lines) + "\n"
