"""The bearer token (made at first start, kept 0600 beside the database) and the operator lock.

The token says "may command this cell at all"; the lock says "this client commands it
now": while one client holds the (expiring) lock, every other client can read but
not command. Nobody holding it, any token holder may command. A token holder may also break
a stale lock, with a reason: its holder's next command (or renewal) is refused with who broke it
and why. The lock's expiry runs on the monotonic clock; only the times shown to people are wall-clock.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import stat
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from cellctl.errors import Conflict, LockHeld

__all__ = ["Broken", "LockBroken", "LockHeld", "OperatorLock", "load_or_create_token", "read_token", "secret_matches",
           "token_matches", "token_path"]

TOKEN_FILE = "daemon.token"
BREAK_HINT = "cellctl lock break --reason TEXT, or POST /lock/break"


def token_path(store_dir: str | Path) -> Path:
    return Path(store_dir) / TOKEN_FILE


MAX_LOCK_TTL_S = 86400.0  # a lock lapses within a day unless renewed, whichever front end took it


def command_line_safe_token(nbytes: int) -> str:
    """A random URL-safe token that never starts with "-", which a command line would take for an option
    (`--token -x...` is an argparse error: one token in 64 would be refused)."""
    while True:
        token = secrets.token_urlsafe(nbytes)
        if not token.startswith("-"):
            return token


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
    token = command_line_safe_token(32)
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
    deadline: float  # monotonic: a wall-clock step neither shortens nor extends the lock
    used: float      # monotonic: when its holder last took, renewed or commanded with it (a break needs it idle)

    def public(self, monotonic: float, wall: float) -> dict:
        """What anyone may see (never the lock id): times for people on the wall clock, as of now."""
        left = max(self.deadline - monotonic, 0.0)
        return {"held": True, "holder": self.holder, "acquired": self.acquired, "expires": wall + left,
                "expires_in_s": round(left, 1), "idle_s": round(monotonic - self.used, 1)}


@dataclass(frozen=True)
class Broken:
    """A lock someone broke: whose it was, who broke it, why, and when (wall clock)."""

    holder: str
    by: str
    reason: str
    at: float

    def public(self) -> dict:
        return {"holder": self.holder, "by": self.by, "reason": self.reason, "at": self.at}


class LockBroken(LockHeld):
    """The lock id presented is one someone broke: its holder is told by whom and why."""

    def __init__(self, broken: Broken):
        at = time.strftime("%H:%M:%S", time.localtime(broken.at))
        super().__init__(f"your operator lock (held as {broken.holder!r}) was broken by {broken.by} at {at}: "
                         f"{broken.reason}; that lock id no longer holds: send commands without it (CLI: unset "
                         "CELLCTL_LOCK), or take the lock anew")
        self.broken = broken


class OperatorLock:
    """Who may command now. Expiry runs on `monotonic`; `wall` only stamps the times shown to people.

    A lock may be broken only once it is stale: its holder has neither renewed it nor commanded with it for
    `break_after_idle_s` (the console renews its lease every 10 s, so an open console's lock is never stale). A
    holder in the middle of an intervention (a job paused while someone is in the cell) keeps it."""

    BROKEN_KEPT = 64  # the last locks broken: presenting one's id is refused with who broke it and why

    def __init__(self, monotonic=time.monotonic, wall=time.time, break_after_idle_s: float = 60.0):
        self._monotonic, self._wall = monotonic, wall
        self.break_after_idle_s = break_after_idle_s
        self._mutex = threading.Lock()
        self._info: LockInfo | None = None
        self._broken: dict[str, Broken] = {}  # sha256 of a broken lock's id -> the break (newest last)

    def _current(self) -> LockInfo | None:
        if self._info is not None and self._info.deadline <= self._monotonic():
            self._info = None  # expired: free again
        return self._info

    def describe(self, info: LockInfo) -> dict:
        """A lock's public status as of now (as `status` gives it)."""
        return info.public(self._monotonic(), self._wall())

    def _refuse_broken(self, lock_id: str | None) -> None:
        broken = self._broken.get(_digest(lock_id)) if lock_id is not None else None
        if broken is not None:
            raise LockBroken(broken)

    def status(self) -> dict:
        with self._mutex:
            info = self._current()
            return self.describe(info) if info else {"held": False}

    def acquire(self, holder: str, ttl_s: float, lock_id: str | None = None) -> LockInfo:
        """Take the lock, or renew it when `lock_id` is the current one; LockHeld if another holds it, LockBroken
        if `lock_id` is one that was broken (a heartbeat must not take back a lock someone broke)."""
        with self._mutex:
            self._refuse_broken(lock_id)
            info = self._current()
            now = self._monotonic()
            if info is not None and (lock_id is None or not secret_matches(lock_id, info.lock_id)):
                raise LockHeld(f"the operator lock is held by {info.holder!r} for {info.deadline - now:.0f} s more"
                               + _present_hint(lock_id))
            if info is not None:
                info.deadline, info.used = now + ttl_s, now
                return info
            self._info = LockInfo(holder, command_line_safe_token(16), self._wall(), now + ttl_s, now)
            return self._info

    def release(self, lock_id: str | None) -> None:
        with self._mutex:
            info = self._current()
            if info is None:
                return
            if lock_id is None or not secret_matches(lock_id, info.lock_id):
                raise LockHeld(f"the operator lock is held by {info.holder!r}; only its holder can release it "
                               f"(if it is stale, break it with a reason: {BREAK_HINT})")
            self._info = None

    def break_lock(self, by: str, reason: str) -> Broken:
        """Free a stale lock whoever holds it (Conflict while it is in use); its holder's id is remembered, so its
        next command is told why."""
        with self._mutex:
            info = self._current()
            if info is None:
                raise Conflict("nobody holds the operator lock: there is nothing to break")
            idle = self._monotonic() - info.used
            if idle < self.break_after_idle_s:
                raise Conflict(f"the operator lock of {info.holder!r} is in use: its holder renewed it or commanded "
                               f"with it {idle:.0f} s ago; a lock can be broken once it has been idle "
                               f"{self.break_after_idle_s:.0f} s (in {self.break_after_idle_s - idle:.0f} s), or ask "
                               "its holder to release it")
            broken = Broken(info.holder, by, reason, self._wall())
            self._broken[_digest(info.lock_id)] = broken
            while len(self._broken) > self.BROKEN_KEPT:
                del self._broken[next(iter(self._broken))]
            self._info = None
            return broken

    def check_held(self, lock_id: str | None, what: str) -> None:
        """`check`, and more: the caller must hold the lock itself (manual motion is for its holder only)."""
        with self._mutex:
            held = self._current() is not None
        if not held:
            self._refuse_broken(lock_id)
            raise LockHeld(f"{what} is for the holder of the operator lock only, and nobody holds it: take it first "
                           "(cellctl lock acquire, then export CELLCTL_LOCK; or Take lock on the console)")
        self.check(lock_id)

    def check(self, lock_id: str | None) -> None:
        """May a client presenting `lock_id` (or none) command the cell now?"""
        with self._mutex:
            self._refuse_broken(lock_id)
            info = self._current()
            if info is None:
                return
            if lock_id is None or not secret_matches(lock_id, info.lock_id):
                raise LockHeld(f"the operator lock is held by {info.holder!r} (expires in "
                               f"{info.deadline - self._monotonic():.0f} s); commands from other clients are "
                               f"refused (a stale lock can be broken with a reason: {BREAK_HINT})"
                               + _present_hint(lock_id))
            info.used = self._monotonic()  # its holder is at work: not stale


def _present_hint(lock_id: str | None) -> str:
    """A command that came with no lock id may be its holder's own, who forgot to present it (the usual slip after
    `cellctl lock acquire`): say how."""
    if lock_id is not None:
        return ""
    return ("; this command presented no lock id: if the lock is yours, present it (on the command line: run the "
            "`export CELLCTL_LOCK=...` line that `cellctl lock acquire` printed)")


def _digest(lock_id: str) -> str:
    """A broken lock's id is looked up by its hash: a dict lookup leaks no timing about the id itself."""
    return hashlib.sha256(lock_id.encode("utf-8", "surrogateescape")).hexdigest()
