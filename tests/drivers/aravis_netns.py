"""Device discovery through Aravis, run inside a network namespace of its own (`unshare -n`).

Discovery broadcasts on every network interface, so it is exercised where `lo` is the only one:
two fake cameras (127.0.0.1 and 127.0.0.2), then the driver chooses among them by serial, model
and index. Prints one JSON object: scenario -> "ok <serial> <address>" or "<ErrorType>: <message>".
Usage (from the project root): unshare -n .venv/bin/python -m tests.drivers.aravis_netns
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile

from drivers.registry import DriverContext, backend_class

from tests.drivers.aravis_fake import FakeGvCamera

SCENARIOS = {
    "serial": {"serial": "NSB"},
    "none": {},
    "model_index": {"model": "Fake", "index": 1},
    "unknown_serial": {"serial": "NOPE"},
}


def main() -> int:
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    subprocess.run(["ip", "addr", "add", "127.0.0.2/8", "dev", "lo"], check=True)
    results = {}
    with tempfile.TemporaryDirectory() as logs:
        fakes = [FakeGvCamera(logs, "NSA", "127.0.0.1"), FakeGvCamera(logs, "NSB", "127.0.0.2")]
        try:
            for fake in fakes:
                fake.start()
            for name, options in SCENARIOS.items():
                camera = backend_class("camera", "genicam").create("cam", {"library": "aravis", **options},
                                                                    DriverContext())
                try:
                    camera.connect()
                    camera.capture()
                    results[name] = f"ok {camera._camera.get_device_serial_number()} {camera._where}"
                except Exception as exc:  # reported to the test, which judges it
                    results[name] = f"{type(exc).__name__}: {exc}"
                finally:
                    camera.close()
        finally:
            for fake in fakes:
                fake.stop()
    print(json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
