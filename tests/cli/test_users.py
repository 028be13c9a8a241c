"""``gateway users add|passwd|remove|list``: the users file through the command line."""

from __future__ import annotations

import json
import stat
from typing import TYPE_CHECKING

import pytest
from typer.testing import CliRunner

from gateway.cli.root import app
from gateway.web.users import USERS_FILE, UserBook

if TYPE_CHECKING:
    from pathlib import Path

    from typer.testing import Result

PASSWORD = "correct horse battery"  # noqa: S105 - the tests' own
OTHER = "staple paper clip"


@pytest.fixture
def config(tmp_path: Path) -> Path:
    path = tmp_path / "gateway.yaml"
    path.write_text(
        "buses: [{name: basin, port: /dev/null}]\n"
        f"state_dir: {json.dumps(str(tmp_path / 'state'))}\n",
        encoding="utf-8",
    )
    return path


def _users(config: Path, *args: str, stdin: str | None = None) -> Result:
    return CliRunner().invoke(app, ["users", *args, "--config", str(config)], input=stdin)


def _book(config: Path) -> UserBook:
    return UserBook(config.parent / "state" / USERS_FILE)


def test_add_asks_twice_with_the_typing_hidden_and_keeps_a_hash(config: Path) -> None:
    result = _users(config, "add", "ana", "--role", "operator", stdin=f"{PASSWORD}\n{PASSWORD}\n")
    assert result.exit_code == 0, result.output
    assert "added ana (operator)" in result.stdout
    assert PASSWORD not in result.output  # hidden: not echoed
    assert result.output.count("Password") == 1
    assert "Repeat for confirmation" in result.output
    book = _book(config)
    assert stat.S_IMODE(book.path.stat().st_mode) == 0o600
    assert PASSWORD not in book.path.read_text(encoding="utf-8")
    user = book.authenticate("ana", PASSWORD)
    assert user is not None
    assert user.role.value == "operator"


def test_a_password_typed_differently_the_second_time_is_asked_again(config: Path) -> None:
    typed = f"{PASSWORD}\n{OTHER}\n{OTHER}\n{OTHER}\n"
    result = _users(config, "add", "ana", "--role", "viewer", stdin=typed)
    assert result.exit_code == 0, result.output
    assert "do not match" in result.output
    assert _book(config).authenticate("ana", OTHER) is not None


def test_a_script_gives_the_password_on_standard_input(config: Path) -> None:
    result = _users(config, "add", "ben", "-r", "admin", "--password-stdin", stdin=f"{OTHER}\n")
    assert result.exit_code == 0, result.output
    assert "Password" not in result.output  # nothing asked
    user = _book(config).authenticate("ben", OTHER)
    assert user is not None
    assert user.role.value == "admin"


def test_an_existing_user_a_bad_role_or_a_short_password_is_refused_with_exit_2(
    config: Path,
) -> None:
    assert (
        _users(config, "add", "ana", "-r", "operator", "--password-stdin", stdin=PASSWORD).exit_code
        == 0
    )
    before = _book(config).path.read_bytes()
    again = _users(config, "add", "ana", "-r", "viewer", "--password-stdin", stdin=OTHER)
    assert again.exit_code == 2
    assert "user 'ana' exists already: use 'gateway users passwd'" in again.stderr
    role = _users(config, "add", "ben", "--role", "root", "--password-stdin", stdin=OTHER)
    assert role.exit_code == 2
    assert "unknown role 'root': one of viewer, operator, admin" in role.stderr
    short = _users(config, "add", "ben", "--role", "viewer", "--password-stdin", stdin="short")
    assert short.exit_code == 2
    assert "the password is too short: at least 8 characters" in short.stderr
    name = _users(config, "add", "Ben Smith", "--role", "viewer", "--password-stdin", stdin=OTHER)
    assert name.exit_code == 2
    assert "user name 'Ben Smith' is not allowed" in name.stderr
    assert _book(config).path.read_bytes() == before  # nothing refused changed the file


def test_passwd_changes_the_password_of_a_user_and_refuses_an_unknown_one(
    config: Path,
) -> None:
    _users(config, "add", "ana", "-r", "operator", "--password-stdin", stdin=PASSWORD)
    changed = _users(config, "passwd", "ana", stdin=f"{OTHER}\n{OTHER}\n")
    assert changed.exit_code == 0, changed.output
    assert "the password of ana is changed" in changed.stdout
    book = _book(config)
    assert book.authenticate("ana", PASSWORD) is None
    assert book.authenticate("ana", OTHER) is not None
    unknown = _users(config, "passwd", "zoe", stdin=f"{OTHER}\n{OTHER}\n")
    assert unknown.exit_code == 2
    assert "no user 'zoe' (users: ana)" in unknown.stderr
    assert "Password" not in unknown.output  # refused before asking


def test_list_shows_names_and_roles_never_a_hash_and_remove_takes_a_user_out(
    config: Path,
) -> None:
    empty = _users(config, "list")
    assert empty.exit_code == 0
    assert "no users in" in empty.stderr
    _users(config, "add", "vic", "-r", "viewer", "--password-stdin", stdin=PASSWORD)
    _users(config, "add", "ana", "-r", "operator", "--password-stdin", stdin=PASSWORD)
    listed = _users(config, "list")
    assert listed.exit_code == 0, listed.output
    assert listed.stdout.split("\n") == ["ana  operator", "vic  viewer", ""]
    assert "scrypt" not in listed.output
    as_json = _users(config, "list", "--json")
    assert json.loads(as_json.stdout) == [
        {"name": "ana", "role": "operator"},
        {"name": "vic", "role": "viewer"},
    ]
    removed = _users(config, "remove", "vic")
    assert removed.exit_code == 0, removed.output
    assert "removed vic (viewer)" in removed.stdout
    assert json.loads(_users(config, "list", "--json").stdout) == [
        {"name": "ana", "role": "operator"}
    ]
    gone = _users(config, "remove", "vic")
    assert gone.exit_code == 2
    assert "no user 'vic' (users: ana)" in gone.stderr


def test_the_file_is_where_web_users_file_says(tmp_path: Path) -> None:
    elsewhere = tmp_path / "etc" / "page-users.json"
    config = tmp_path / "gateway.yaml"
    config.write_text(
        "buses: [{name: basin, port: /dev/null}]\n"
        f"web: {{users_file: {json.dumps(str(elsewhere))}}}\n",
        encoding="utf-8",
    )
    result = _users(config, "add", "ana", "-r", "operator", "--password-stdin", stdin=PASSWORD)
    assert result.exit_code == 0, result.output
    assert UserBook(elsewhere).authenticate("ana", PASSWORD) is not None
    broken = _users(tmp_path / "missing.yaml", "list")
    assert broken.exit_code == 2
