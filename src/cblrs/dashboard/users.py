"""The dashboard's users file: who may log in, with which role, and their API tokens.

A YAML file written by ``cblrs dashboard-users`` (never by hand-copied secrets), 0600::

    version: 1
    users:
      alice:
        role: admin                       # viewer | admin
        password: scrypt$131072$8$1$<salt>$<hash>
        tokens:                           # for scripts: Authorization: Bearer <token>
          - {label: grafana, sha256: <hex>, created: 2025-05-01T10:00:00Z}

Passwords are stored as scrypt hashes (:func:`hash_password`: RFC 7914 through
:func:`hashlib.scrypt`, N=2^17, r=8, p=1, a 16-byte random salt, the parameters kept in the
string so that stronger ones can come later); tokens are 256-bit random strings shown once
and stored as their SHA-256 (a token is as long as a key, so a fast hash cannot be
guessed back). Nothing in the file lets anyone log in without the password or token.

Roles: a ``viewer`` sees the map, the live streams and the replays; an ``admin`` also uses
the calibration page and saves calibrations (and whatever else changes the site).
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import os
import re
import secrets
import stat
import tempfile
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from enum import IntEnum
from pathlib import Path
from typing import Any

import yaml

from cblrs.errors import CblrsError

SCRYPT_N = 2**17
SCRYPT_R = 8
SCRYPT_P = 1
SCRYPT_MAXMEM = 256 * 2**20
PASSWORD_MIN = 10
PASSWORD_MAX = 1024
TOKEN_PREFIX = "cblrs_"
USER_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@-]{0,63}$")


class UsersError(CblrsError):
    """The users file or a change to it is refused (one sentence)."""


class Role(IntEnum):
    """What a user may do; a higher role may do all a lower one may."""

    VIEWER = 1
    ADMIN = 2

    @classmethod
    def parse(cls, text: str) -> Role:
        try:
            return cls[str(text).upper()]
        except KeyError:
            raise UsersError(f"role {text!r} is not viewer or admin.") from None

    @property
    def label(self) -> str:
        return self.name.lower()


@dataclass(frozen=True)
class Token:
    """An API token's record (the token itself is never stored)."""

    label: str
    sha256: str
    created: str


@dataclass(frozen=True)
class User:
    """One user's record.

    Attributes:
        name: the login name.
        role: viewer or admin.
        password: the scrypt hash string ("" when the user logs in by token only).
        tokens: the user's API tokens.
    """

    name: str
    role: Role
    password: str = ""
    tokens: tuple[Token, ...] = field(default=())

    @property
    def stamp(self) -> str:
        """Changes whenever the role, password or tokens change (a session opened with an
        older stamp ends)."""
        text = f"{self.role.label}\n{self.password}\n" + "\n".join(t.sha256 for t in self.tokens)
        return hashlib.sha256(text.encode()).hexdigest()


# ---------------------------------------------------------------------------- hashing


def hash_password(password: str) -> str:
    """The scrypt hash string of ``password`` (``scrypt$N$r$p$salt$hash``, base64 parts)."""
    check_password_text(password)
    salt = secrets.token_bytes(16)
    digest = hashlib.scrypt(password.encode(), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P,
                            maxmem=SCRYPT_MAXMEM, dklen=32)
    return "$".join(["scrypt", str(SCRYPT_N), str(SCRYPT_R), str(SCRYPT_P),
                     _b64(salt), _b64(digest)])


def verify_password(password: str, stored: str) -> bool:
    """Whether ``password`` matches the hash string ``stored`` (constant-time compare).

    An empty or malformed ``stored`` never matches; the work is done all the same, so that
    an unknown user takes as long to refuse as a wrong password.
    """
    parts = stored.split("$") if stored else []
    try:
        if len(parts) != 6 or parts[0] != "scrypt":
            raise ValueError
        n, r, p = (int(value) for value in parts[1:4])
        salt, expected = _unb64(parts[4]), _unb64(parts[5])
        if not (2 <= n <= 2**20 and 1 <= r <= 32 and 1 <= p <= 16 and len(expected) >= 16):
            raise ValueError
    except ValueError:
        n, r, p, salt, expected = SCRYPT_N, SCRYPT_R, SCRYPT_P, b"\0" * 16, b""
    if len(password) > PASSWORD_MAX:
        return False
    digest = hashlib.scrypt(password.encode(), salt=salt, n=n, r=r, p=p, maxmem=SCRYPT_MAXMEM,
                            dklen=len(expected) or 32)
    return bool(expected) and hmac.compare_digest(digest, expected)


def check_password_text(password: str, user: str | None = None) -> None:
    """Refuse a password too short, too long, or equal to the user's name."""
    if len(password) < PASSWORD_MIN:
        raise UsersError(f"a password needs at least {PASSWORD_MIN} characters.")
    if len(password) > PASSWORD_MAX:
        raise UsersError(f"a password has at most {PASSWORD_MAX} characters.")
    if user is not None and password.lower() == user.lower():
        raise UsersError("the password must not be the user name.")


def new_token() -> str:
    """A new random API token (shown once; store only :func:`token_digest`)."""
    return TOKEN_PREFIX + secrets.token_urlsafe(32)


def token_digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode().rstrip("=")


def _unb64(text: str) -> bytes:
    try:
        return base64.b64decode(text + "=" * (-len(text) % 4), validate=True)
    except (ValueError, TypeError):
        raise ValueError(text) from None


# ---------------------------------------------------------------------------- the file


class UsersFile:
    """The users of one users file (read with :meth:`load`, changed and :meth:`save`-d).

    Args:
        path: the YAML file.
        users: its users by name.
    """

    def __init__(self, path: Path, users: dict[str, User] | None = None):
        self.path = Path(path)
        self.users: dict[str, User] = dict(users or {})

    # -- reading ---------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path, missing_ok: bool = False) -> UsersFile:
        """Read ``path``.

        Args:
            missing_ok: a missing file is an empty one (``dashboard-users add`` creates it).

        Raises:
            UsersError: unreadable, malformed, or writable by others (someone else could
                make themselves an admin).
        """
        path = Path(path)
        if not path.exists():
            if missing_ok:
                return cls(path)
            raise UsersError(f"users file {path} does not exist; create it with "
                             "cblrs dashboard-users add.")
        check_private(path)
        try:
            data = yaml.safe_load(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as error:
            raise UsersError(f"cannot read users file {path}: {error}.") from None
        return cls(path, _parse(data, path))

    def find_token(self, token: str) -> User | None:
        """The user whose API token ``token`` is, if any."""
        digest = token_digest(token)
        found = None
        for user in self.users.values():
            for record in user.tokens:
                if hmac.compare_digest(record.sha256, digest):
                    found = user
        return found

    # -- changing --------------------------------------------------------------------------
    def add(self, name: str, role: Role, password: str) -> User:
        check_user_name(name)
        if name in self.users:
            raise UsersError(f"user {name!r} exists already in {self.path}; use passwd or "
                             "set-role to change it.")
        check_password_text(password, name)
        user = User(name, role, hash_password(password))
        self.users[name] = user
        return user

    def set_password(self, name: str, password: str) -> User:
        user = self.get(name)
        check_password_text(password, name)
        self.users[name] = replace(user, password=hash_password(password))
        return self.users[name]

    def set_role(self, name: str, role: Role) -> User:
        self.users[name] = replace(self.get(name), role=role)
        return self.users[name]

    def remove(self, name: str) -> None:
        self.get(name)
        del self.users[name]

    def add_token(self, name: str, label: str) -> str:
        """A new token for user ``name`` (returned once; only its hash is kept)."""
        user = self.get(name)
        if not label or not re.fullmatch(r"[A-Za-z0-9._@-]{1,64}", label):
            raise UsersError(f"token label {label!r} must be 1-64 letters, digits or ._@-.")
        if any(record.label == label for record in user.tokens):
            raise UsersError(f"user {name!r} has a token labelled {label!r} already; revoke "
                             "it first or choose another label.")
        token = new_token()
        created = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
        record = Token(label, token_digest(token), created)
        self.users[name] = replace(user, tokens=(*user.tokens, record))
        return token

    def revoke_token(self, name: str, label: str) -> None:
        user = self.get(name)
        kept = tuple(record for record in user.tokens if record.label != label)
        if len(kept) == len(user.tokens):
            raise UsersError(f"user {name!r} has no token labelled {label!r}.")
        self.users[name] = replace(user, tokens=kept)

    def get(self, name: str) -> User:
        try:
            return self.users[name]
        except KeyError:
            raise UsersError(f"no user {name!r} in {self.path}.") from None

    def save(self) -> None:
        """Write the file atomically, readable by its owner only (0600)."""
        document: dict[str, Any] = {"version": 1, "users": {}}
        for user in self.users.values():
            entry: dict[str, Any] = {"role": user.role.label}
            if user.password:
                entry["password"] = user.password
            if user.tokens:
                entry["tokens"] = [{"label": t.label, "sha256": t.sha256, "created": t.created}
                                   for t in user.tokens]
            document["users"][user.name] = entry
        text = ("# cblrs dashboard users (cblrs dashboard-users): scrypt password hashes and "
                "SHA-256 token hashes\n" + yaml.safe_dump(document, sort_keys=False))
        folder = self.path.parent
        folder.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(prefix=f".{self.path.name}.", dir=folder)
        try:
            os.fchmod(handle, 0o600)
            with os.fdopen(handle, "w", encoding="utf-8") as stream:
                stream.write(text)
            os.replace(temporary, self.path)
        except BaseException:
            Path(temporary).unlink(missing_ok=True)
            raise


def check_user_name(name: str) -> None:
    if not USER_NAME.fullmatch(name):
        raise UsersError(f"user name {name!r} must be 1-64 letters, digits or ._@- (starting "
                         "with a letter or digit).")


def check_private(path: Path) -> None:
    """Refuse a users file that others may write (they could add an admin)."""
    try:
        mode = path.stat().st_mode
    except OSError as error:
        raise UsersError(f"cannot read users file {path}: {error.strerror}.") from None
    if mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise UsersError(f"users file {path} is writable by other users; chmod 600 {path}.")


def _parse(data: Any, path: Path) -> dict[str, User]:
    if not isinstance(data, dict) or data.get("version") != 1 \
            or not isinstance(data.get("users") or {}, dict):
        raise UsersError(f"users file {path} is not a cblrs users file (version: 1, users: "
                         "{name: {role, password}}).")
    users: dict[str, User] = {}
    for name, entry in (data.get("users") or {}).items():
        where = f"users file {path}: user {name!r}"
        try:
            check_user_name(str(name))
        except UsersError as error:
            raise UsersError(f"users file {path}: {error}") from None
        if not isinstance(entry, dict) or set(entry) - {"role", "password", "tokens"}:
            raise UsersError(f"{where} must be a mapping with role, password and tokens.")
        role = Role.parse(str(entry.get("role", "")))
        password = str(entry.get("password") or "")
        if password and not password.startswith("scrypt$"):
            raise UsersError(f"{where}: the password is not a scrypt hash (set it with "
                             "cblrs dashboard-users passwd; never write a password here).")
        tokens = []
        for record in entry.get("tokens") or []:
            if not isinstance(record, dict) or not re.fullmatch(r"[0-9a-f]{64}",
                                                                str(record.get("sha256"))):
                raise UsersError(f"{where}: each token needs label and sha256 (64 hex digits).")
            tokens.append(Token(str(record.get("label", "")), str(record["sha256"]),
                                str(record.get("created", ""))))
        users[str(name)] = User(str(name), role, password, tuple(tokens))
    return users
