"""A run made once per test run and read by several test modules. With several workers (pytest-xdist, tools/test)
the first worker to need it makes it while the others wait on a file lock, then every one reads what it left (as
tests/conftest.py's calibrated_cell): a module's own fixture then takes a copy of the store, so what its tests save
stays out of the other modules' inputs."""

from __future__ import annotations

import fcntl
import pickle
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class SharedRun:
    """A routine's run folder, its (closed) store and its result."""

    folder: Path
    store_path: Path
    result: dict

    def store_copy(self, where: Path):
        """A module's own copy of the store (a CalibrationStore)."""
        return copy_store(self.store_path, where)


def copy_store(store_path: Path, where: Path):
    """A copy of a shared run's closed store, opened (a CalibrationStore): what the copy's user saves stays out
    of the other users' inputs."""
    from cellctl.stores.calibrations import CalibrationStore

    shutil.copytree(store_path, where)
    return CalibrationStore(where)


def made_once(request, tmp_path_factory, name: str, make: Callable[[Path, Path], dict]) -> SharedRun:
    """make(run folder, store folder) once per test run; it returns the run's result and closes its store."""
    shared = tmp_path_factory.getbasetemp()
    if hasattr(request.config, "workerinput"):  # an xdist worker
        shared = shared.parent  # the run's folder, above each worker's own
    folder = shared / name
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        done = folder / "result.pickle"
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)  # a run that died half-way
            folder.mkdir()
            result = make(folder / "run", folder / "store")
            done.write_bytes(pickle.dumps(result))
        result = pickle.loads(done.read_bytes())
    return SharedRun(folder / "run", folder / "store", result)
