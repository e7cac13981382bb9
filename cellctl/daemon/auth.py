"""The bearer token (made at first start, kept 0600 beside the database) and the operator lock.

The token says "may command this cell at all"; the lock says "this client commands it
now": while one client holds the (expiring) lock, every other client can read but
not command. Nobody holding it, any token holder may command.
"""

from __future__ import annotations

import hmac
import os
import secrets
import stat
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from ..errors import LockHeld

__all__ = ["LockHeld", "OperatorLock", "load_or_create_token", "read_token", "secret_matches", "token_matches",
           "token_path"]

TOKEN_FILE = "daemon.token"


def token_path(store_dir: str | Path) -> Path:
    return Path(store_dir) / TOKEN_FILE


def load_or_create_token(store_dir: str | Path) -> str:
    """The daemon's token; created (0600, owner only) if there is none yet."""
    path = token_path(store_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        if stat.S_IMODE(path.stat().st_mode) & 0o077:
            os.chmod(path, 0o600)  # someone loosened it: the token is a password, tighten it again
        return read_token(store_dir)
    token = secrets.token_urlsafe(32)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
        f.flush()
        os.fsync(f.fileno())
    return token


def read_token(store_dir: str | Path) -> str:
    path = token_path(store_dir)
    try:
        token = path.read_text().strip()
    except FileNotFoundError:
        raise FileNotFoundError(f"no token at {path}: start the daemon once (cellctl serve) to create it") from None
    if not token:
        raise ValueError(f"{path} is empty; delete it and restart the daemon to make a new token")
    return token


def secret_matches(given: str, secret: str) -> bool:
    """Constant-time comparison of what a client sent with a secret, as UTF-8 bytes.

    `hmac.compare_digest` refuses str with non-ASCII characters (TypeError); a header may carry any
    (Latin-1 decoded), and such a value must simply not match."""
    return hmac.compare_digest(given.encode("utf-8", "surrogateescape"), secret.encode("utf-8"))


def token_matches(given: str, token: str) -> bool:
    return secret_matches(given, token)


@dataclass
class LockInfo:
    holder: str
    lock_id: str
    acquired: float  # wall clock, for people
    expires: float   # wall clock

    def public(self) -> dict:
        return {"held": True, "holder": self.holder, "acquired": self.acquired, "expires": self.expires,
                "expires_in_s": round(max(self.expires - time.time(), 0.0), 1)}


class OperatorLock:
    def __init__(self, clock=time.time):
        self._clock = clock
        self._mutex = threading.Lock()
        self._info: LockInfo | None = None

    def _current(self) -> LockInfo | None:
        if self._info is not None and self._info.expires <= self._clock():
            self._info = None  # expired: free again
        return self._info

    def status(self) -> dict:
        with self._mutex:
            info = self._current()
            return info.public() if info else {"held": False}

    def acquire(self, holder: str, ttl_s: float, lock_id: str | None = None) -> LockInfo:
        """Take the lock, or renew it when `lock_id` is the current one; LockHeld if another holds it."""
        with self._mutex:
            info = self._current()
            t = self._clock()
            if info is not None and (lock_id is None or not secret_matches(lock_id, info.lock_id)):
                raise LockHeld(f"the operator lock is held by {info.holder!r} for {info.expires - t:.0f} s more")
            if info is not None:
                info.expires = t + ttl_s
                return info
            self._info = LockInfo(holder, secrets.token_urlsafe(16), t, t + ttl_s)
            return self._info

    def release(self, lock_id: str | None) -> None:
        with self._mutex:
            info = self._current()
            if info is None:
                return
            if lock_id is None or not secret_matches(lock_id, info.lock_id):
                raise LockHeld(f"the operator lock is held by {info.holder!r}; only its holder can release it")
            self._info = None

    def check(self, lock_id: str | None) -> None:
        """May a client presenting `lock_id` (or none) command the cell now?"""
        with self._mutex:
            info = self._current()
            if info is not None and (lock_id is None or not secret_matches(lock_id, info.lock_id)):
                raise LockHeld(f"the operator lock is held by {info.holder!r} (expires in "
                               f"{info.expires - self._clock():.0f} s); commands from other clients are refused")
