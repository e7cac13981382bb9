"""One process owns a cell: its store folder and each device endpoint it drives.

Two processes driving one arm is a safety defect (UR's RTDE and dashboard, like ABB's socket link, accept
several clients), and a second writer of the store changes calibrations the daemon's audit never sees. So
`cellctl serve` and an in-process `cellctl run` first take the cell: an exclusive `flock` on
`<store>/owner.lock`, and one per device endpoint in the machine's lock folder (/run/lock, or
$CELLCTL_LOCK_DIR), so two cell files naming one robot cannot both drive it; a local write of the store alone
(`calibrations activate`, `opcua trust`, `fleet restore`) takes the store's lock only. Endpoints are named by
the drivers' Settings (see `endpoints`); a camera chosen by index or model is not locked. A lock is taken
without waiting, held for the process's life and released by the kernel when the process ends, kill -9
included: a crash leaves no stale owner to clear. The lock file records the
owner (pid, since when, the command, its URL once serving) so that a refusal names it and says how to go
through it; the file stays when the owner ends, only the lock on it counts.

Read-only verbs take nothing: SQLite (WAL) lets them read beside the owner. Ports are the kernel's own
lock: `listening_socket` claims one before any device is touched and, when it is taken, says what holds it
as far as /proc tells.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
import stat
import sys
import tempfile
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path

from drivers.registry import backend_class

from cellctl.errors import Conflict, InvalidRequest

OWNER_FILE = "owner.lock"


@dataclass(frozen=True)
class Owner:
    """What a lock file records about the process holding it."""

    pid: int
    host: str
    since: str  # UTC, to the second
    command: str
    store: str
    url: str | None = None

    def describe(self) -> str:
        where = "" if self.host == socket.gethostname() else f" on {self.host}"
        serving = f", serving {self.url}" if self.url else ""
        return f"pid {self.pid}{where} ({self.command}, since {self.since}{serving})"


class CellOwned(Conflict):
    """Another process owns the cell (its store, or a device endpoint it drives); nothing was touched."""

    def __init__(self, what: str, owner: Owner | None, store: Path | None = None,
                 verb: str | None = "cellctl run ROUTINE"):
        self.owner = owner
        self.store = store  # set when the store itself is owned: the same cell, whose daemon can run the job
        holder = owner.describe() if owner else "another process (its record is not written yet)"
        if verb is None:  # the verb cannot go through an owner (e.g. a restore needs a store no one uses)
            how = "stop it first, or choose another store"
        elif owner and owner.url:
            how = f"go through it: {verb} --url {owner.url} (or export CELLCTL_URL={owner.url})"
        elif owner and owner.command.startswith("cellctl serve"):
            how = ("it is starting: once it serves (its URL is then in the store's daemon.url), go through it with "
                   "--url URL or $CELLCTL_URL")
        else:
            how = "it serves no API to go through: wait for it to end, or stop it, then try again"
        super().__init__(f"{what} is owned by {holder}; {how}")


class Ownership:
    """The locks this process holds on a cell; `release()` (or the process's end) gives them back."""

    def __init__(self, command: str, store: Path, verb: str | None = "cellctl run ROUTINE"):
        self.verb = verb  # what a refusal tells to go through the owner
        self.owner = Owner(os.getpid(), socket.gethostname(),
                           datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC"), command, str(store))
        self._held: list[int] = []  # open lock files (closing one releases its lock)

    def claim(self, path: Path, what: str, store: Path | None = None, for_all_users: bool = False) -> None:
        """Lock `path` for this process, or CellOwned naming its holder (what is already held is given back)."""
        try:
            fd = _open_lock_file(path, for_all_users)
        except OSError as exc:  # e.g. the store of a daemon's service user: only its daemon can be asked
            self.release()
            raise InvalidRequest(f"{what}: cannot open its lock {path}: {exc.strerror or exc}; if another user's "
                                 "daemon owns it, go through it: --url URL or $CELLCTL_URL") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_owner(fd)
            os.close(fd)
            self.release()
            raise CellOwned(what, holder, store, self.verb) from None
        self._held.append(fd)
        _write_owner(fd, self.owner)

    def serving(self, url: str) -> None:
        """Record the URL a refused process is told to go through."""
        self.owner = Owner(**{**asdict(self.owner), "url": url})
        for fd in self._held:
            _write_owner(fd, self.owner)

    def release(self) -> None:
        for fd in self._held:
            os.close(fd)
        self._held.clear()

    def __enter__(self) -> Ownership:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def own_store(store: Path, command: str, verb: str | None = "cellctl run ROUTINE") -> Ownership:
    """This process owns the cell's store (to write it beside no other owner); else CellOwned, whose hint tells
    to run `verb` through the owner (None: it cannot be)."""
    store = Path(store)
    owned = Ownership(command, store, verb)
    owned.claim(store / OWNER_FILE, f"the cell's store {store}", store=store)
    return owned


def own_cell(config, store: Path, command: str) -> Ownership:
    """This process owns the cell: its store, then each device endpoint of the cell file; else CellOwned."""
    owned = own_store(store, command)
    for device, endpoint in endpoints(config):
        owned.claim(lock_dir() / f"cellctl-endpoint-{_file_name(endpoint)}.lock",
                    f"device endpoint {endpoint} ({device})", for_all_users=True)
    return owned


# -- device endpoints ------------------------------------------------------------------------------------------

def endpoints(config) -> list[tuple[str, str]]:
    """(device name, endpoint) of each device endpoint the cell drives, as its driver's Settings name it
    (drivers/endpoint.py: defaults filled in, hosts resolved, device paths followed). Simulated backends drive
    nothing outside this process; a camera chosen by index, by model or as "the only one" is not locked, as
    nothing names it the same way in another process."""
    found = []
    for kind, name, dev in config.devices():
        settings = backend_class(kind, dev.backend).Settings(**dev.options)  # parse_cell_file validated them
        found += [(name, endpoint) for endpoint in getattr(settings, "endpoints", list)()]
    return found


def lock_dir() -> Path:
    """Where endpoint locks live: shared by every user and service of this machine."""
    chosen = os.environ.get("CELLCTL_LOCK_DIR")
    if chosen:
        return Path(chosen)
    run_lock = Path("/run/lock")
    return run_lock if os.access(run_lock, os.W_OK | os.X_OK) else Path(tempfile.gettempdir())


def _file_name(endpoint: str) -> str:
    return "".join(c if c.isalnum() or c in ".-" else "_" for c in endpoint)


# -- the lock file -----------------------------------------------------------------------------------------------


def _open_lock_file(path: Path, for_all_users: bool) -> int:
    """Open (or create) a regular lock file, never through a symlink. `for_all_users`: in a folder of every
    user, so made readable and writable by all (a service's umask is 0077; the record is no secret), and never
    opened with O_CREAT once it exists (Linux's protected_regular refuses that on another user's file in a
    sticky folder)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_NOFOLLOW)
        except PermissionError:
            fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)  # not writable to us: it still locks
        except FileNotFoundError:
            try:
                fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
            except FileExistsError:
                continue  # made in between: open it as it is
            if for_all_users:
                os.fchmod(fd, 0o666)
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise OSError(errno.EINVAL, "not a regular file")
        return fd


def _write_owner(fd: int, owner: Owner) -> None:
    """Record the owner, in a file of this process's user only (another's file is left as it is: the lock
    holds all the same). Written before it is cut to length, so a reader never sees an empty record."""
    record = (json.dumps(asdict(owner)) + "\n").encode()
    try:
        if os.fstat(fd).st_uid != os.geteuid():
            return
        os.pwrite(fd, record, 0)
        os.ftruncate(fd, len(record))
    except OSError:  # opened read-only
        pass


def _read_owner(fd: int) -> Owner | None:
    try:
        owner = Owner(**json.loads(os.pread(fd, 65536, 0)))
    except (OSError, ValueError, TypeError):  # not written yet, or by another version
        return None
    # Another user's file keeps its maker's record (we write only our own): a dead pid is not the holder.
    return None if owner.host == socket.gethostname() and not _alive(owner.pid) else owner


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


# -- ports -----------------------------------------------------------------------------------------------------


class PortInUse(InvalidRequest):
    """A TCP port this process is to listen on is taken (the message says by what, when /proc tells)."""

    def __init__(self, what: str, host: str, port: int, fix: str, address: str | None = None):
        holder = port_holder(address or host, port)
        super().__init__(f"{what}: port {port} on {host} is in use{f' by {holder}' if holder else ''}; {fix}")
        self.host, self.port = host, port


def listening_socket(host: str, port: int, what: str, fix: str) -> socket.socket:
    """A socket listening on host:port (SO_REUSEADDR, as servers bind), or PortInUse / InvalidRequest."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)[0]
    except socket.gaierror as exc:
        raise InvalidRequest(f"{what}: host {host!r} is not an address of this machine ({exc.strerror})") from None
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(2048)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise PortInUse(what, host, port, fix, address[0]) from None
        raise InvalidRequest(f"{what}: cannot listen on {host}:{port}: {exc.strerror or exc}; {fix}") from None
    return sock


def check_port_free(host: str, port: int, what: str, fix: str) -> None:
    """PortInUse now if something listens on host:port (port 0, a free one, is always free)."""
    if port:
        listening_socket(host, port, what, fix).close()


def port_holder(address: str, port: int) -> str | None:
    """'pid N (command)' of the process listening on TCP address:port (or on every address at that port), as
    far as /proc tells this user."""
    inodes = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            rows = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            fields = row.split()
            if len(fields) <= 9 or fields[3] != "0A":  # not listening
                continue
            where, at = fields[1].rsplit(":", 1)
            if int(at, 16) == port and _proc_address(where) in (address, "0.0.0.0", "::"):
                inodes.add(f"socket:[{fields[9]}]")
    if not inodes:
        return None
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            fds = list((proc / "fd").iterdir())
        except OSError:  # another user's process, or gone
            continue
        if any(_link(fd) in inodes for fd in fds):
            try:
                command = " ".join((proc / "cmdline").read_bytes().decode(errors="replace").replace("\0", " ").split())
            except OSError:  # gone meanwhile
                command = "?"
            return f"pid {proc.name} ({command[:120]})"
    return "a process of another user"


def _link(fd: Path) -> str | None:
    """Where a /proc fd points; None once it is closed (a busy process opens and closes files all the time)."""
    try:
        return os.readlink(fd)
    except OSError:
        return None


def _proc_address(hex_address: str) -> str:
    """An address as /proc/net/tcp{,6} writes it: 32-bit words in the host's byte order."""
    raw = bytes.fromhex(hex_address)
    words = raw if sys.byteorder == "big" else b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))
    return socket.inet_ntop(socket.AF_INET if len(raw) == 4 else socket.AF_INET6, words)
