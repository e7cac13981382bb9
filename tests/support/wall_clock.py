"""A wall clock a test can step under a real process (the daemon), as NTP steps a cell PC's clock after a week
offline: wall_clock_step.c, built here and preloaded into the process, adds an offset read from a file to the wall
clock at every call. The monotonic clock, and every wait and sleep on it, is left alone."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

SOURCE = Path(__file__).with_name("wall_clock_step.c")


def compiler() -> str | None:
    return shutil.which("cc") or shutil.which("gcc")


class SteppedWallClock:
    """The wall-clock offset of the processes started with `env()`, stepped with `step`."""

    def __init__(self, folder: Path):
        cc = compiler()
        if cc is None:
            raise FileNotFoundError("no C compiler to build tests/support/wall_clock_step.c: run tools/ensure-system")
        self.library = Path(folder) / "wall_clock_step.so"
        subprocess.run([cc, "-shared", "-fPIC", "-O2", "-o", str(self.library), str(SOURCE), "-ldl"], check=True)
        self.file = Path(folder) / "wall_clock_offset"
        self.offset_s = 0
        self._write()

    def env(self) -> dict[str, str]:
        preload = " ".join(p for p in (str(self.library), os.environ.get("LD_PRELOAD", "")) if p)
        return {"LD_PRELOAD": preload, "CELLCTL_WALL_OFFSET_FILE": str(self.file)}

    def step(self, seconds: int) -> None:
        """Set the wall clock `seconds` on (back, if negative) from where it is, at once."""
        self.offset_s += int(seconds)
        self._write()

    def _write(self) -> None:
        tmp = self.file.with_suffix(".tmp")
        tmp.write_text(f"{self.offset_s}\n")
        os.replace(tmp, self.file)  # whole: the process reads the file at every call and must never see half of it
