"""Credentials of the plant's servers: from a file only its owner may read (0600), or from the environment.

The value is only ever handed to the library that uses it; errors name the file or the variable, never what
it holds (`scrub` takes it out of a server's error text too)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from cellctl.errors import InvalidRequest


class CredentialError(InvalidRequest):
    """A credential that cannot be had, or that is kept where others can read it."""


def from_file(path: str | Path, what: str, base: Path | None = None) -> str:
    path = Path(path).expanduser()
    if not path.is_absolute() and base is not None:
        path = base / path
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise CredentialError(f"{what}: the file {path} does not exist") from None
    except PermissionError:
        raise CredentialError(f"{what}: the file {path} cannot be read by this user") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise CredentialError(f"{what}: the file {path} may be read by others (mode {stat.S_IMODE(mode):04o}); "
                              f"allowed: owner-only, chmod 600 {path}")
    try:
        value = path.read_text().strip()
    except (PermissionError, UnicodeDecodeError) as exc:
        raise CredentialError(f"{what}: the file {path} cannot be read ({type(exc).__name__})") from None
    if not value:
        raise CredentialError(f"{what}: the file {path} is empty")
    return value


def from_env(name: str, what: str) -> str:
    value = os.environ.get(name, "").strip()
    if not value:
        raise CredentialError(f"{what}: the environment variable {name} is not set")
    return value


def read(what: str, file: str | None, env: str | None, base: Path | None = None) -> str | None:
    """The credential from `file` or `env` (the cell file gives at most one); None if it gives neither."""
    if file is not None:
        return from_file(file, what, base)
    if env is not None:
        return from_env(env, what)
    return None


def scrub(text: str, *secrets: str | None) -> str:
    """`text` with every secret (and a DSN's password) replaced by ***."""
    for secret in secrets:
        if secret:
            text = text.replace(secret, "***")
            password = _dsn_password(secret)
            if password:
                text = text.replace(password, "***")
    return text


def _dsn_password(dsn: str) -> str | None:
    """The password in a DSN, URI (postgresql://user:pw@host/db) or key=value form (password=pw)."""
    try:
        from psycopg.conninfo import conninfo_to_dict

        return conninfo_to_dict(dsn).get("password")
    except Exception:  # noqa: BLE001 - not a DSN: nothing more to hide
        return None
