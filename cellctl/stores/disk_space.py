"""Free space on the store's filesystem: measured, refused below a floor, and named when a write ran out of it.

The daemon refuses new jobs, resumptions and `save_images` while the store's filesystem has less free space than
the cell file's `store: {min_free_mb}` (InsufficientStorage, HTTP 507). A write that fails mid-job for lack of
space (ENOSPC or EDQUOT from the OS, SQLITE_FULL from SQLite) ends the job faulted with a `DiskFull` that names
the filesystem and what fills it: the store's biggest parts, and what lies outside the store.

A reserve file (RESERVE_FILE, RESERVE_MB) is kept in the store while there is room for it: when a write fails for
lack of space, the daemon deletes it first, so that the job's fault, its audit and the outbox's record of it can
still be written. It is made again once the free space is back above the floor.
"""

from __future__ import annotations

import errno
import os
import sqlite3
from dataclasses import dataclass
from pathlib import Path

from cellctl.errors import InsufficientStorage

RESERVE_FILE = ".disk-reserve"
RESERVE_MB = 8.0
MB = 1 << 20
# the store's parts named when the disk fills: (label, glob patterns under the store)
PARTS = (("images", ("jobs/*/images", "jobs/*/*/images")),
         ("run folders (samples, results, reports)", ("jobs",)),
         ("daemon.sqlite", ("daemon.sqlite", "daemon.sqlite-wal", "daemon.sqlite-shm")),
         ("calibrations.sqlite", ("calibrations.sqlite", "calibrations.sqlite-wal", "calibrations.sqlite-shm")),
         ("calibration samples", ("samples",)))


class DiskFull(InsufficientStorage):
    """A write failed for lack of space (ENOSPC, EDQUOT, SQLITE_FULL): the job faults with this, naming the
    filesystem and what fills it; what was written before the failure is kept."""


@dataclass(frozen=True)
class Space:
    """The store's filesystem: where it is mounted, its type, and its total and free bytes (free for this user)."""

    store: Path
    mount: str
    fs_type: str
    total: int
    free: int  # what the daemon may still write (f_bavail)
    used: int  # what files take (blocks the filesystem keeps for root are neither)

    @property
    def free_mb(self) -> float:
        return self.free / MB

    @property
    def filesystem(self) -> str:
        return f"{self.fs_type} on {self.mount}"

    def to_dict(self, min_free_mb: float) -> dict:
        return {"path": str(self.store), "filesystem": self.filesystem, "free_mb": round(self.free_mb, 1),
                "total_mb": round(self.total / MB, 1), "min_free_mb": min_free_mb,
                "low": self.free_mb < min_free_mb}


def free_bytes(path: Path) -> int:
    """What this user may still write on `path`'s filesystem (f_bavail)."""
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


def space(store: Path) -> Space:
    """statvfs of the store's filesystem."""
    st = os.statvfs(store)
    mount = _mount_point(Path(store).resolve())
    return Space(Path(store), str(mount), _fs_type(mount), st.f_blocks * st.f_frsize, st.f_bavail * st.f_frsize,
                 (st.f_blocks - st.f_bfree) * st.f_frsize)


def _mount_point(path: Path) -> Path:
    while not os.path.ismount(path) and path != path.parent:
        path = path.parent
    return path


def _fs_type(mount: Path) -> str:
    try:
        with open("/proc/self/mounts") as f:
            types = [line.split()[2] for line in f if len(line.split()) > 2 and line.split()[1] == str(mount)]
    except OSError:
        return "filesystem"
    return types[-1] if types else "filesystem"  # the last mount on a point is the one seen


def require_free(store: Path, min_free_mb: float, what: str) -> Space:
    """The store's space, or InsufficientStorage (507) naming the free space, the floor and the filesystem when
    there is less than `min_free_mb` free; `what`: the refused request ("a new job"). The reserve file is made
    again here once there is room for it."""
    found = space(store)
    if found.free_mb < min_free_mb:
        raise InsufficientStorage(
            f"{what} is refused: the store's filesystem ({found.filesystem}, holding {store}) has "
            f"{found.free_mb:.1f} MB free, below the {min_free_mb:g} MB the cell file asks to keep free "
            f"(store.min_free_mb); {usage(store, found)}. Free space there (delete old images or run folders, "
            "or move the store to a larger disk), then try again")
    keep_reserve(store)
    return found


def is_disk_full(exc: BaseException) -> bool:
    """Was `exc` (or what it was raised from) a write that ran out of space?"""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, DiskFull):
            return True
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if isinstance(exc, sqlite3.Error) and (getattr(exc, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL
                                               or "database or disk is full" in str(exc)):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def disk_full(store: Path, exc: BaseException) -> DiskFull:
    """The DiskFull for a write that failed with `exc`: the filesystem, its free space and what fills it. The
    reserve file is deleted first, so that the fault itself can be recorded."""
    release_reserve(store)
    try:
        found = space(store)
    except OSError:
        return DiskFull(f"no space left on the store's filesystem (holding {store}) ({exc})")
    return DiskFull(f"no space left on the store's filesystem ({found.filesystem}, holding {store}): "
                    f"{type(exc).__name__}: {exc}; {usage(store, found)}. Every sample written before is kept: "
                    "free space there, then acknowledge and resume the job")


def usage(store: Path, found: Space) -> str:
    """What fills the filesystem, in words: the store's biggest parts, and what lies outside the store."""
    sizes = {label: sum(tree_size(p) for pattern in patterns for p in Path(store).glob(pattern)) for label, patterns
             in PARTS}
    sizes["run folders (samples, results, reports)"] -= sizes["images"]
    in_store = tree_size(Path(store)) - tree_size(Path(store) / RESERVE_FILE)
    used = found.used
    parts = ", ".join(f"{label} {n / MB:.1f} MB" for label, n in sorted(sizes.items(), key=lambda kv: -kv[1]) if n)
    return (f"{used / MB:.1f} of its {found.total / MB:.1f} MB are used: the store holds {in_store / MB:.1f} MB "
            f"({parts or 'nothing yet'}), and {max(used - in_store, 0) / MB:.1f} MB lie outside the store")


def tree_size(path: Path) -> int:
    """Bytes a file or folder tree takes (files that vanish meanwhile count nothing)."""
    try:
        if path.is_symlink() or not path.is_dir():
            return path.lstat().st_size if path.exists() or path.is_symlink() else 0
    except OSError:
        return 0
    total = 0
    for root, _dirs, files in os.walk(path, onerror=lambda _e: None):
        for name in files:
            try:
                total += os.lstat(os.path.join(root, name)).st_size
            except OSError:
                pass
    return total


def keep_reserve(store: Path) -> bool:
    """Make the reserve file if it is missing and there is room for it beside the space it must leave; True if
    it is there now."""
    path = Path(store) / RESERVE_FILE
    size = int(RESERVE_MB * MB)
    try:
        if path.exists() and path.stat().st_size >= size:
            return True
        if free_bytes(store) < 2 * size:
            return False
        fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o600)
        try:
            os.posix_fallocate(fd, 0, size)  # real blocks, not a sparse file: deleting it frees them
            os.fsync(fd)
        finally:
            os.close(fd)
        return True
    except OSError:
        path.unlink(missing_ok=True)
        return False


def release_reserve(store: Path) -> None:
    (Path(store) / RESERVE_FILE).unlink(missing_ok=True)
