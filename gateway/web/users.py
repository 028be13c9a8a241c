"""The page's named users: who they are, what their role lets them do, their password's hash.

21 CFR Part 11 §11.10(d) and §11.300 ask that only the people authorised sign in, each
under a name of their own, so that a record says who did it and not just "someone with
the password". The users live in one JSON file (``web.users_file``, by default
``users.json`` in the state directory) that ``gateway users`` edits and the page reads::

    {"version": 1, "users": [
        {"name": "ana", "role": "operator", "password": "scrypt$16384$8$1$<salt>$<hash>"}]}

A password is kept only as a slow, salted hash: :func:`hashlib.scrypt` (RFC 7914) with a
random salt of its own, so two users with the same password have different hashes and a
stolen file costs a guesser tens of milliseconds and 16 MiB per guess, not the
nanoseconds of a plain SHA-256. The hash names its parameters (``scrypt$N$r$p$...``),
so they can be raised later without locking anyone out: an old hash is still checked
with the parameters it was made with. Hashes are compared with
:func:`hmac.compare_digest`.

The file is written whole to a temporary file beside it, flushed to the disk and renamed
over the old one, with mode 0600: a power cut leaves either the old users or the new, and
no other account on the machine can read the hashes. A removed user is gone from the
file; their name stays on the records they made.

The running gateway reads the file again when it changes (:meth:`UserBook.snapshot`), so
``gateway users add`` takes effect at the next sign-in, without a restart or a reload.
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import functools
import hashlib
import hmac
import json
import logging
import os
import re
import secrets
import tempfile
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Final

from gateway.errors import CommandRejectedError, ConfigError

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.config import WebConfig

_LOGGER = logging.getLogger(__name__)

USERS_FILE: Final = "users.json"  # in the state directory, unless web.users_file says where
FILE_VERSION: Final = 1
FILE_MODE: Final = 0o600
MIN_PASSWORD: Final = 8  # NIST SP 800-63B 5.1.1.2: at least 8 characters chosen by a person
MAX_PASSWORD: Final = 1024  # a longer "password" is an attempt to make the hash slow
NAME_PATTERN: Final = re.compile(r"[a-z0-9][a-z0-9._-]{0,31}")
NAME_RULE: Final = (
    "1 to 32 characters: lower-case letters, digits, '.', '_' and '-', starting with a "
    "letter or a digit"
)
# scrypt's cost: N = 2**14, r = 8, p = 1 (RFC 7914 section 2's interactive example; the
# Python documentation's too): 16 MiB and some 50 ms per check on a Raspberry Pi 4.
SCRYPT_N: Final = 2**14
SCRYPT_R: Final = 8
SCRYPT_P: Final = 1
SALT_BYTES: Final = 16
HASH_BYTES: Final = 32
# Bounds on what a hash in the file may ask for, so a file edited by hand cannot make a
# sign-in take minutes or gigabytes.
MAX_N: Final = 2**20
MAX_R: Final = 32
MAX_P: Final = 16


class Role(StrEnum):
    """What a user may do on the page."""

    VIEWER = "viewer"  # reads
    OPERATOR = "operator"  # reads, writes, calibrates, verifies
    ADMIN = "admin"  # what an operator may, and whatever is administrative

    @property
    def rank(self) -> int:
        """The order of the roles: each may do what the ones below it may."""
        return _RANKS[self]

    def allows(self, needed: Role) -> bool:
        """Whether this role may do what ``needed`` may."""
        return self.rank >= needed.rank

    @classmethod
    def parse(cls, text: str) -> Role:
        """The role of that name, or a :class:`CommandRejectedError` listing the roles."""
        try:
            return cls(text.strip().lower())
        except ValueError:
            roles = ", ".join(role.value for role in cls)
            raise CommandRejectedError(f"unknown role {text!r}: one of {roles}") from None


_RANKS: Final = {Role.VIEWER: 0, Role.OPERATOR: 1, Role.ADMIN: 2}


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def _scrypt(password: bytes, salt: bytes, *, n: int, r: int, p: int, length: int) -> bytes:
    # scrypt needs 128 * r * N bytes; OpenSSL's default cap (32 MiB) would refuse a raised N.
    return hashlib.scrypt(
        password, salt=salt, n=n, r=r, p=p, maxmem=2 * 128 * r * n + 2**20, dklen=length
    )


@dataclass(frozen=True, slots=True, kw_only=True)
class PasswordHash:
    """A password as the gateway keeps it: scrypt's parameters, the salt and the hash."""

    n: int
    r: int
    p: int
    salt: bytes
    hash: bytes

    @classmethod
    def of(cls, secret: str | bytes) -> PasswordHash:
        """The hash of ``secret`` with a new random salt and today's parameters."""
        data = secret.encode("utf-8") if isinstance(secret, str) else secret
        salt = secrets.token_bytes(SALT_BYTES)
        hashed = _scrypt(data, salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P, length=HASH_BYTES)
        return cls(n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P, salt=salt, hash=hashed)

    @classmethod
    def parse(cls, text: str) -> PasswordHash:
        """Read ``scrypt$N$r$p$<salt>$<hash>`` (base64); a :class:`ValueError` says why not."""
        parts = text.split("$")
        if len(parts) != 6 or parts[0] != "scrypt":  # noqa: PLR2004 - the format's six fields
            raise ValueError("not a hash of the form scrypt$N$r$p$salt$hash")
        try:
            n, r, p = (int(part) for part in parts[1:4])
            salt = base64.b64decode(parts[4], validate=True)
            hashed = base64.b64decode(parts[5], validate=True)
        except (ValueError, binascii.Error) as exc:
            raise ValueError(f"a field of the hash cannot be read: {exc}") from None
        if n < 2 or n > MAX_N or n & (n - 1) or not 1 <= r <= MAX_R or not 1 <= p <= MAX_P:  # noqa: PLR2004
            raise ValueError(f"scrypt parameters out of bounds: N={n}, r={r}, p={p}")
        if len(salt) < SALT_BYTES or len(hashed) < 16:  # noqa: PLR2004
            raise ValueError("the salt or the hash is too short")
        return cls(n=n, r=r, p=p, salt=salt, hash=hashed)

    def matches(self, secret: str | bytes) -> bool:
        """Whether ``secret`` hashes to this (slow on purpose; compared in constant time)."""
        data = secret.encode("utf-8") if isinstance(secret, str) else secret
        if len(data) > MAX_PASSWORD * 4:
            return False
        given = _scrypt(data, self.salt, n=self.n, r=self.r, p=self.p, length=len(self.hash))
        return hmac.compare_digest(given, self.hash)

    def __str__(self) -> str:
        """The self-describing form kept in the file."""
        return f"scrypt${self.n}${self.r}${self.p}${_b64(self.salt)}${_b64(self.hash)}"

    def __repr__(self) -> str:
        """Parameters only: a hash has no business in a log line."""
        return f"PasswordHash(scrypt N={self.n} r={self.r} p={self.p})"


@functools.cache
def _nobody() -> PasswordHash:
    """The hash checked when a name is not in the file.

    So an unknown name takes as long to refuse as a wrong password: the time an answer
    takes tells nothing of which names exist. Made at the first need, not at import.
    """
    return PasswordHash.of(secrets.token_bytes(16))


def check_name(name: str) -> str:
    """``name`` as kept (lower case, trimmed), or a :class:`CommandRejectedError` saying why."""
    kept = name.strip().lower()
    if not NAME_PATTERN.fullmatch(kept):
        raise CommandRejectedError(f"user name {name!r} is not allowed: {NAME_RULE}")
    return kept


def check_password(password: str) -> str:
    """``password`` if it is long enough (and not absurdly long), else why not."""
    if len(password) < MIN_PASSWORD:
        raise CommandRejectedError(
            f"the password is too short: at least {MIN_PASSWORD} characters "
            "(a few words are easier to remember than symbols)"
        )
    if len(password) > MAX_PASSWORD:
        raise CommandRejectedError(f"the password is too long: at most {MAX_PASSWORD} characters")
    return password


@dataclass(frozen=True, slots=True, kw_only=True)
class User:
    """One named user of the page."""

    name: str
    role: Role
    password: PasswordHash

    def as_dict(self) -> dict[str, str]:
        """The user as the file keeps them."""
        return {"name": self.name, "role": self.role.value, "password": str(self.password)}


def users_path(config: WebConfig, state_dir: Path) -> Path:
    """Where the users file is: ``web.users_file``, else ``users.json`` in ``state_dir``."""
    return config.users_file if config.users_file is not None else state_dir / USERS_FILE


class UserBook:
    """The users file: read, checked, and written whole and atomically."""

    def __init__(self, path: Path) -> None:
        """The file at ``path`` (it need not exist yet: then there are no users)."""
        self.path = path
        self._seen: tuple[int, int, int] | None = None  # (inode, size, mtime) last read
        self._users: Mapping[str, User] = {}
        self._warned = False

    # --- reading ----------------------------------------------------------------------

    def load(self) -> dict[str, User]:
        """Every user by name; none if the file does not exist; a :class:`ConfigError` if bad."""
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return {}
        except OSError as exc:
            raise ConfigError(f"cannot read {self.path}: {exc}", key="web.users_file") from exc
        return self._parse(text)

    def _parse(self, text: str) -> dict[str, User]:
        def bad(message: str) -> ConfigError:
            return ConfigError(f"{self.path}: {message}", key="web.users_file")

        try:
            document = json.loads(text)
        except ValueError as exc:
            raise bad(f"not JSON: {exc}") from None
        if not isinstance(document, dict) or not isinstance(document.get("users"), list):
            raise bad('expected {"version": 1, "users": [...]}')
        if document.get("version") != FILE_VERSION:
            raise bad(f"version {document.get('version')!r}: this gateway reads {FILE_VERSION}")
        users: dict[str, User] = {}
        for index, entry in enumerate(document["users"]):
            if not isinstance(entry, dict):
                raise bad(f"users[{index}] is not an object")
            try:
                name = check_name(str(entry.get("name", "")))
                user = User(
                    name=name,
                    role=Role.parse(str(entry.get("role", ""))),
                    password=PasswordHash.parse(str(entry.get("password", ""))),
                )
            except (CommandRejectedError, ValueError) as exc:
                raise bad(f"users[{index}]: {exc}") from None
            if name in users:
                raise bad(f"users[{index}]: {name!r} is there twice")
            users[name] = user
        return users

    def snapshot(self) -> Mapping[str, User]:
        """The users as the file holds them now, read again only when it changed.

        For the running page: a file that cannot be read (a half-edited copy put there by
        hand) is a warning, and the users last read stay, so nobody is locked out by it.
        """
        try:
            stat = self.path.stat()
        except FileNotFoundError:
            self._seen, self._users = None, {}
            return self._users
        except OSError as exc:
            self._warn(f"cannot read {self.path}: {exc}")
            return self._users
        seen = (stat.st_ino, stat.st_size, stat.st_mtime_ns)
        if seen != self._seen:
            try:
                users = self.load()
            except ConfigError as exc:
                self._warn(str(exc))
                return self._users
            self._seen, self._users, self._warned = seen, users, False
            _LOGGER.info("web: %d user(s) in %s", len(users), self.path)
        return self._users

    def _warn(self, message: str) -> None:
        level = logging.DEBUG if self._warned else logging.WARNING
        _LOGGER.log(level, "web: the users file: %s; the users read before stay", message)
        self._warned = True

    def authenticate(self, name: str, password: str) -> User | None:
        """The user if ``password`` is theirs, else ``None``; slow (run it in a thread).

        An unknown name costs the same scrypt as a known one.
        """
        try:
            kept = check_name(name)
        except CommandRejectedError:
            kept = ""
        user = self.snapshot().get(kept)
        if user is None:
            _nobody().matches(password)
            return None
        return user if user.password.matches(password) else None

    # --- writing ----------------------------------------------------------------------

    def add(self, name: str, role: Role, password: str) -> User:
        """A new user; refused if the name is taken, not allowed, or the password short."""
        users = self.load()
        kept = check_name(name)
        if kept in users:
            raise CommandRejectedError(f"user {kept!r} exists already: use 'gateway users passwd'")
        user = User(name=kept, role=role, password=PasswordHash.of(check_password(password)))
        users[kept] = user
        self._save(users)
        return user

    def set_password(self, name: str, password: str) -> User:
        """A new password (and a new salt) for a user who exists."""
        users = self.load()
        old = self._existing(users, name)
        hashed = PasswordHash.of(check_password(password))
        user = User(name=old.name, role=old.role, password=hashed)
        users[user.name] = user
        self._save(users)
        return user

    def remove(self, name: str) -> User:
        """A user gone from the file (their name stays on the records they made)."""
        users = self.load()
        user = self._existing(users, name)
        del users[user.name]
        self._save(users)
        return user

    @staticmethod
    def _existing(users: Mapping[str, User], name: str) -> User:
        user = users.get(name.strip().lower())
        if user is None:
            known = ", ".join(sorted(users)) or "none yet"
            raise CommandRejectedError(f"no user {name!r} (users: {known})")
        return user

    def _save(self, users: Mapping[str, User]) -> None:
        """Write the whole file: a temporary file, flushed, renamed over; mode 0600."""
        document = {
            "version": FILE_VERSION,
            "users": [users[name].as_dict() for name in sorted(users)],
        }
        text = json.dumps(document, indent=2) + "\n"
        directory = self.path.parent
        try:
            directory.mkdir(parents=True, exist_ok=True)
            # mkstemp creates the file 0600 from the start: the hashes are never readable
            # by others, not even for the moment before a chmod.
            handle, temporary = tempfile.mkstemp(prefix=f".{self.path.name}.", dir=directory)
            try:
                with os.fdopen(handle, "w", encoding="utf-8") as file:
                    file.write(text)
                    file.flush()
                    os.fsync(file.fileno())
                os.chmod(temporary, FILE_MODE)  # noqa: PTH101 - the path of a mkstemp
                _keep_owner(temporary, self.path)
                Path(temporary).replace(self.path)
            except BaseException:
                with contextlib.suppress(OSError):
                    Path(temporary).unlink()
                raise
            directory_handle = os.open(directory, os.O_RDONLY)
            try:
                os.fsync(directory_handle)  # the rename itself on the disk
            finally:
                os.close(directory_handle)
        except OSError as exc:
            raise ConfigError(f"cannot write {self.path}: {exc}", key="web.users_file") from exc


def _keep_owner(temporary: str, path: Path) -> None:
    """The new file owned as the old one was (else as its directory), when run as root.

    ``sudo gateway users add`` must not leave a file of root's, 0600, that the service's
    own user can no longer read.
    """
    if os.geteuid() != 0:
        return
    try:
        owner = path.stat() if path.exists() else path.parent.stat()
        os.chown(temporary, owner.st_uid, owner.st_gid)
    except OSError as exc:
        _LOGGER.warning("cannot give %s the owner of the file it replaces: %s", path, exc)
