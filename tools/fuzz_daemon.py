"""Fuzz the daemon's API from its own OpenAPI schema (schemathesis): no request may get a 5xx.

    .venv/bin/python tools/fuzz_daemon.py [--max-examples 25] [-- more `st run` options]

Starts a daemon on the simulated micro cell (temporary store, ephemeral port), runs
`st run` with the token against /openapi.json (the event stream left out: `st run`
reads a body to its end, and the stream never ends), and stops the daemon. For
longer runs than the test suite's: tests/daemon/test_fuzz.py fuzzes every operation,
/events included, in-process with a bounded number of examples. schemathesis is in
the `test` extra (a development tool, not a runtime dependency).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "daemon"))

from daemon_helpers import DaemonProcess, write_cell_file


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--max-examples", type=int, default=25)
    parser.add_argument("--checks", default="not_a_server_error")
    parser.add_argument("extra", nargs="*", help="more options for `st run`")
    args = parser.parse_args()
    st = shutil.which("st", path=str(Path(sys.executable).parent)) or shutil.which("st")
    if not st:
        print("schemathesis is not installed (pip install -e '.[test]')", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        daemon = DaemonProcess(write_cell_file(Path(tmp), realtime_factor=0.0)).start()
        try:
            cmd = [st, "run", f"{daemon.url}/openapi.json", "-H", f"Authorization: Bearer {daemon.token}",
                   "--exclude-path", "/events", "--checks", args.checks, "--max-examples", str(args.max_examples),
                   *args.extra]
            status = subprocess.call(cmd)
            errors = [e for e in daemon.logs() if e.get("level") == "error"]
            print(f"daemon logged {len(errors)} errors")
            return status or (1 if errors else 0)
        finally:
            daemon.terminate()
            daemon.log.close()


if __name__ == "__main__":
    sys.exit(main())
