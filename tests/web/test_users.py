"""The page's users file: scrypt with a salt each, mode 0600, written whole, read again when changed."""

from __future__ import annotations

import hashlib
import json
import os
import stat
from typing import TYPE_CHECKING

import pytest

from gateway.config import WebConfig, parse_config
from gateway.errors import CommandRejectedError, ConfigError
from gateway.records.actor import SHARED_PASSWORD, Via
from gateway.web import Sessions
from gateway.web.users import (
    MIN_PASSWORD,
    USERS_FILE,
    PasswordHash,
    Role,
    UserBook,
    users_path,
)

if TYPE_CHECKING:
    from pathlib import Path

PASSWORD = "correct horse battery"  # noqa: S105 - the tests' own
OTHER = "staple paper clip"


@pytest.fixture
def book(tmp_path: Path) -> UserBook:
    return UserBook(tmp_path / "state" / USERS_FILE)


def _stored(book: UserBook) -> dict[str, str]:
    document = json.loads(book.path.read_text(encoding="utf-8"))
    return {user["name"]: user["password"] for user in document["users"]}


def test_passwords_are_kept_as_scrypt_with_a_salt_of_their_own(book: UserBook) -> None:
    book.add("ana", Role.OPERATOR, PASSWORD)
    book.add("ben", Role.VIEWER, PASSWORD)  # the same password
    stored = _stored(book)
    assert stored["ana"].startswith("scrypt$16384$8$1$")
    assert stored["ana"] != stored["ben"]  # salted: the same password, two hashes
    ana, ben = PasswordHash.parse(stored["ana"]), PasswordHash.parse(stored["ben"])
    assert ana.salt != ben.salt
    assert len(ana.salt) == 16
    text = book.path.read_text(encoding="utf-8")
    assert PASSWORD not in text
    assert hashlib.sha256(PASSWORD.encode()).hexdigest() not in text  # never a plain hash
    assert repr(ana) == "PasswordHash(scrypt N=16384 r=8 p=1)"  # no salt, no hash in a log


def test_the_right_password_signs_in_a_wrong_one_or_an_unknown_name_does_not(
    book: UserBook,
) -> None:
    book.add("ana", Role.OPERATOR, PASSWORD)
    user = book.authenticate("ana", PASSWORD)
    assert user is not None
    assert (user.name, user.role) == ("ana", Role.OPERATOR)
    assert book.authenticate(" Ana ", PASSWORD) is not None  # a phone's capital and space
    assert book.authenticate("ana", PASSWORD + " ") is None
    assert book.authenticate("ana", OTHER) is None
    assert book.authenticate("nobody", PASSWORD) is None
    assert book.authenticate("not a name!", PASSWORD) is None


def test_the_file_is_mode_0600_and_replaced_whole_by_a_rename(book: UserBook) -> None:
    book.add("ana", Role.OPERATOR, PASSWORD)
    assert stat.S_IMODE(book.path.stat().st_mode) == 0o600
    before = book.path.read_text(encoding="utf-8")
    old = book.path.with_name("old-copy")
    os.link(book.path, old)  # a second name for the file as it is now
    book.add("ben", Role.VIEWER, OTHER)
    # Written to a new file and renamed over: the old file was never opened for writing,
    # so a reader (or a power cut) sees the old users or the new, never half of them.
    assert old.read_text(encoding="utf-8") == before
    assert book.path.stat().st_ino != old.stat().st_ino
    assert sorted(_stored(book)) == ["ana", "ben"]
    assert stat.S_IMODE(book.path.stat().st_mode) == 0o600
    assert sorted(p.name for p in book.path.parent.iterdir()) == ["old-copy", USERS_FILE]


def test_a_file_that_cannot_be_written_is_a_config_error_and_leaves_nothing(
    tmp_path: Path,
) -> None:
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("", encoding="utf-8")
    book = UserBook(blocker / USERS_FILE)
    with pytest.raises(ConfigError, match=r"web\.users_file: cannot read"):
        book.add("ana", Role.OPERATOR, PASSWORD)
    with pytest.raises(ConfigError, match=r"web\.users_file: cannot write"):
        book._save({})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["not-a-directory"]


def test_names_passwords_and_roles_are_checked_with_a_reason(book: UserBook) -> None:
    with pytest.raises(CommandRejectedError, match=f"at least {MIN_PASSWORD} characters"):
        book.add("ana", Role.OPERATOR, "short")
    with pytest.raises(CommandRejectedError, match="is not allowed: 1 to 32 characters"):
        book.add("ana lopes", Role.OPERATOR, PASSWORD)
    with pytest.raises(CommandRejectedError, match="is not allowed"):
        book.add("-ana", Role.OPERATOR, PASSWORD)
    with pytest.raises(CommandRejectedError, match="unknown role 'root': one of viewer, operator"):
        Role.parse("root")
    assert not book.path.exists()  # nothing refused was written
    book.add("Ana", Role.OPERATOR, PASSWORD)  # kept in lower case
    with pytest.raises(CommandRejectedError, match="'ana' exists already"):
        book.add("ana", Role.VIEWER, OTHER)
    with pytest.raises(CommandRejectedError, match=r"no user 'ben' \(users: ana\)"):
        book.set_password("ben", OTHER)
    assert Role.ADMIN.allows(Role.OPERATOR)
    assert Role.OPERATOR.allows(Role.VIEWER)
    assert not Role.VIEWER.allows(Role.OPERATOR)


def test_a_new_password_has_a_new_salt_and_a_removed_user_is_gone(book: UserBook) -> None:
    book.add("ana", Role.OPERATOR, PASSWORD)
    first = _stored(book)["ana"]
    book.set_password("ana", PASSWORD)  # the same password again
    assert _stored(book)["ana"] != first
    assert book.authenticate("ana", PASSWORD) is not None
    book.set_password("ana", OTHER)
    assert book.authenticate("ana", PASSWORD) is None
    assert book.authenticate("ana", OTHER) is not None
    assert book.remove("ana").name == "ana"
    assert _stored(book) == {}
    assert book.authenticate("ana", OTHER) is None


def test_a_hash_made_with_other_parameters_is_still_checked_with_its_own(
    book: UserBook,
) -> None:
    salt = os.urandom(16)
    cheap = hashlib.scrypt(PASSWORD.encode(), salt=salt, n=2**10, r=4, p=1, dklen=32)
    hashed = PasswordHash(n=2**10, r=4, p=1, salt=salt, hash=cheap)
    book.path.parent.mkdir(parents=True)
    document = {"version": 1, "users": [{"name": "ana", "role": "admin", "password": str(hashed)}]}
    book.path.write_text(json.dumps(document), encoding="utf-8")
    user = book.authenticate("ana", PASSWORD)
    assert user is not None
    assert user.role is Role.ADMIN
    for bad in ("scrypt$1000$8$1$AAAA$AAAA", "scrypt$16384$99$1$AAAA$AAAA", "sha256$abc"):
        with pytest.raises(ValueError, match=r"scrypt|bounds|form"):
            PasswordHash.parse(bad)


def test_the_running_page_reads_the_file_again_and_keeps_the_last_good_one(
    book: UserBook, caplog: pytest.LogCaptureFixture
) -> None:
    assert book.snapshot() == {}
    book.add("ana", Role.OPERATOR, PASSWORD)
    assert list(book.snapshot()) == ["ana"]
    book.path.write_text("{half a file", encoding="utf-8")
    assert list(book.snapshot()) == ["ana"]  # nobody locked out by a broken edit
    assert "the users file" in caplog.text
    assert "the users read before stay" in caplog.text
    with pytest.raises(ConfigError, match="not JSON"):
        book.load()  # the command line says it plainly


def test_the_file_is_in_the_state_directory_unless_web_users_file_says(tmp_path: Path) -> None:
    config = parse_config("buses: [{name: basin, port: /dev/null}]\n", environ={})
    assert config.web.users_file is None
    assert users_path(config.web, tmp_path) == tmp_path / USERS_FILE
    elsewhere = tmp_path / "etc" / "users.json"
    config = parse_config(
        f"buses: [{{name: basin, port: /dev/null}}]\nweb: {{users_file: {elsewhere}}}\n",
        environ={},
    )
    assert users_path(config.web, tmp_path) == elsewhere


def test_sessions_of_named_users_have_their_role_and_the_shared_password_is_operator(
    book: UserBook,
) -> None:
    book.add("ana", Role.OPERATOR, PASSWORD)
    book.add("vic", Role.VIEWER, OTHER)
    config = WebConfig.model_validate({"enabled": True, "password": "shared secret"})
    keeper = Sessions.from_config(config, users=book)
    assert keeper.enabled
    viewer = keeper.sign_in("vic", OTHER, "192.0.2.7")
    assert viewer is not None
    assert (viewer.user, viewer.role, viewer.shared) == ("vic", Role.VIEWER, False)
    shared = keeper.sign_in("  Ana   Lopes ", "shared secret", "192.0.2.8")
    assert shared is not None
    assert (shared.user, shared.who, shared.role) == (SHARED_PASSWORD, "Ana Lopes", Role.OPERATOR)
    actor = shared.actor("192.0.2.8", reason="weekly check", signed=True)
    assert (actor.user, actor.via, actor.reason, actor.signed) == (
        SHARED_PASSWORD,
        Via.PAGE,
        "weekly check",
        True,
    )
    assert actor.detail == "192.0.2.8, name given: Ana Lopes"
    assert keeper.signature_ok(shared, "shared secret")
    assert not keeper.signature_ok(shared, PASSWORD)
    assert keeper.signature_ok(viewer, OTHER)
    assert not keeper.signature_ok(viewer, "shared secret")
    # A role changed in the file is the session's at its next request; a removed user's
    # session ends.
    book.remove("vic")
    book.add("vic", Role.OPERATOR, OTHER)
    found = keeper.find(viewer.token)
    assert found is not None
    assert found.role is Role.OPERATOR
    book.remove("vic")
    assert keeper.find(viewer.token) is None
    assert keeper.find(shared.token) is shared


def test_the_shared_password_is_kept_as_scrypt_also_when_configured_as_sha256() -> None:
    digest = hashlib.sha256(b"shared secret").hexdigest()
    config = WebConfig.model_validate({"enabled": True, "password_sha256": digest})
    keeper = Sessions.from_config(config)
    assert isinstance(keeper._shared, PasswordHash)
    assert keeper._shared.hash != bytes.fromhex(digest)
    assert keeper.sign_in("ana", "shared secret", "127.0.0.1") is not None
    assert keeper.sign_in("ana", digest, "127.0.0.1") is None  # the digest is no password
