"""``gateway users``: the page's named users and their roles, kept in the users file.

``add NAME --role ROLE``, ``passwd NAME``, ``remove NAME`` and ``list`` edit and show the
file the page signs users in from (:mod:`gateway.web.users`: ``web.users_file``, by
default ``users.json`` in the state directory), found through ``--config`` as every
command finds the gateway's files. A running gateway reads the file again at the next
sign-in: no restart, no reload.

The password is asked for twice with the typing hidden, or read from the first line of
standard input with ``--password-stdin`` (for scripts; never as an argument, which every
user of the machine can read in the process list). ``list`` shows names and roles, never
a hash. Exit codes: 0 done; 2 refused with nothing changed (an unknown or existing user,
a bad role, name or password, a config with a problem); 1 the users file cannot be read
or written.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Final

import typer

from gateway.app import state_directory
from gateway.cli.device import err, fail, out
from gateway.config import load_config
from gateway.errors import CommandRejectedError, ConfigError, GatewayError
from gateway.web.users import MIN_PASSWORD, Role, UserBook, users_path

DEFAULT_CONFIG: Final = Path("/etc/rs485-gateway/gateway.yaml")  # deploy/systemd's

users_app = typer.Typer(
    help="The web page's named users and their roles (viewer, operator, admin).",
    no_args_is_help=True,
)

ConfigOption = Annotated[
    Path,
    typer.Option("--config", "-c", help="The gateway's YAML config (it says where the file is)."),
]
NameArgument = Annotated[str, typer.Argument(help="The user's name (lower case, digits, . _ -).")]
PasswordStdinOption = Annotated[
    bool,
    typer.Option(
        "--password-stdin", help="Read the password from the first line of standard input."
    ),
]


def register(app: typer.Typer) -> None:
    """Add ``users`` to the ``gateway`` command line."""
    app.add_typer(users_app, name="users")


def _book(config: Path) -> UserBook:
    """The users file of the gateway that ``config`` configures."""
    try:
        settings = load_config(config)
    except GatewayError as exc:
        raise fail(exc) from exc
    return UserBook(users_path(settings.web, state_directory(settings)))


def _password(*, from_stdin: bool) -> str:
    """The new password: standard input's first line, or asked twice with the typing hidden."""
    if from_stdin:
        return sys.stdin.readline().removesuffix("\n").removesuffix("\r")
    return str(
        typer.prompt(
            f"Password (at least {MIN_PASSWORD} characters)",
            hide_input=True,
            confirmation_prompt=True,
        )
    )


def _failed(exc: GatewayError) -> typer.Exit:
    """Refused (2, nothing changed) or the file failed (1)."""
    return fail(exc, code=1 if isinstance(exc, ConfigError) else 2)


@users_app.command("add")
def add(
    name: NameArgument,
    role: Annotated[
        str,
        typer.Option("--role", "-r", help="viewer (reads), operator (writes, calibrates), admin."),
    ],
    config: ConfigOption = DEFAULT_CONFIG,
    password_stdin: PasswordStdinOption = False,
) -> None:
    """Add a user with a role; the password is asked for twice."""
    try:
        chosen = Role.parse(role)
        book = _book(config)
        if name.strip().lower() in book.load():  # said before the password is asked for
            raise CommandRejectedError(
                f"user {name.strip().lower()!r} exists already: use 'gateway users passwd'"
            )
        user = book.add(name, chosen, _password(from_stdin=password_stdin))
    except GatewayError as exc:
        raise _failed(exc) from exc
    out.print(f"added {user.name} ({user.role.value}) to {book.path}", markup=False)


@users_app.command("passwd")
def passwd(
    name: NameArgument,
    config: ConfigOption = DEFAULT_CONFIG,
    password_stdin: PasswordStdinOption = False,
) -> None:
    """Set a user's password; the new one is asked for twice."""
    try:
        book = _book(config)
        users = book.load()
        if name.strip().lower() not in users:  # said before the password is asked for
            known = ", ".join(sorted(users)) or "none yet"
            raise CommandRejectedError(f"no user {name!r} (users: {known})")
        user = book.set_password(name, _password(from_stdin=password_stdin))
    except GatewayError as exc:
        raise _failed(exc) from exc
    out.print(f"the password of {user.name} is changed", markup=False)


@users_app.command("remove")
def remove(name: NameArgument, config: ConfigOption = DEFAULT_CONFIG) -> None:
    """Remove a user; the records they made keep their name."""
    try:
        book = _book(config)
        user = book.remove(name)
    except GatewayError as exc:
        raise _failed(exc) from exc
    out.print(f"removed {user.name} ({user.role.value}) from {book.path}", markup=False)


@users_app.command("list")
def list_users(
    config: ConfigOption = DEFAULT_CONFIG,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON: [{name, role}].")] = False,
) -> None:
    """List the users and their roles (never their password hashes)."""
    try:
        book = _book(config)
        users = book.load()
    except GatewayError as exc:
        raise _failed(exc) from exc
    rows = [{"name": name, "role": users[name].role.value} for name in sorted(users)]
    if as_json:
        sys.stdout.write(json.dumps(rows) + "\n")
        return
    if not rows:
        err.print(
            f"no users in {book.path}: add one with 'gateway users add NAME --role operator'",
            markup=False,
        )
        return
    width = max(len(row["name"]) for row in rows)
    for row in rows:
        out.print(f"{row['name']:<{width}}  {row['role']}", markup=False)
