"""Run schemathesis's own runner (`st run`) against a daemon: for longer runs than the test suite's.

    .venv/bin/python tools/fuzz_daemon.py [--max-examples 25] [--checks ...] [-- more `st run` options]

Starts a daemon on the simulated micro cell (temporary store, ephemeral port) with one finished job (so
job 1 and calibration 1 exist), runs `st run` with the token against its /openapi.json with the checks
of tests/daemon/test_api_contract.py (all phases, the stateful one too), and stops the daemon. This file is
also `st run`'s hooks file (SCHEMATHESIS_HOOKS): after each call it undoes a taken lock or a submitted
job as the test does, and it reads the OpenCV FileStorage YAML of the calibration export (its
!!opencv-matrix tags are no plain YAML, and schemathesis's YAML reader raises on them). The event stream
never ends: it is read until it has been quiet for 0.2 s. schemathesis is in the `test` extra.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import requests
import schemathesis
import yaml
from schemathesis.core.media_types import YAML_MEDIA_TYPES

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the tests' helpers: tests.support

from tests.support.api_contract import CHECKS, finish_one_job, undo
from tests.support.daemon import DaemonProcess, write_cell_file

EVENTS_CONFIG = '[[operations]]\ninclude-path = "/events"\nrequest-timeout = 0.2\n'


class OpenCVLoader(yaml.SafeLoader):
    """YAML with OpenCV's matrices (!!opencv-matrix: rows, cols, dt, data) read as plain maps."""


OpenCVLoader.add_constructor("tag:yaml.org,2002:opencv-matrix", lambda loader, node: loader.construct_mapping(node))


@schemathesis.deserializer(*YAML_MEDIA_TYPES)  # all: the first of the YAML family registered is the one used
def opencv_yaml(ctx, response):
    try:
        return yaml.load(response.content.decode(response.encoding or "utf-8"), OpenCVLoader)
    except yaml.YAMLError as exc:
        raise ValueError(f"not YAML: {exc}") from None


@schemathesis.hook
def after_call(context, case, response) -> None:
    undo(requests, os.environ["CELLCTL_URL"], os.environ["CELLCTL_TOKEN"], case.method, case.path, response)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--max-examples", type=int, default=25)
    parser.add_argument("--checks", default=",".join(check.__name__ for check in CHECKS))
    parser.add_argument("extra", nargs="*", help="more options for `st run`")
    args = parser.parse_args()
    st = shutil.which("st", path=str(Path(sys.executable).parent)) or shutil.which("st")
    if not st:
        print("schemathesis is not installed (pip install -e '.[test]')", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        daemon = DaemonProcess(write_cell_file(Path(tmp), realtime_factor=0.0)).start()
        try:
            finish_one_job(daemon)
            config = Path(tmp) / "schemathesis.toml"
            config.write_text(EVENTS_CONFIG)
            cmd = [st, "--config-file", str(config), "run", f"{daemon.url}/openapi.json",
                   "-H", f"Authorization: Bearer {daemon.token}", "--checks", args.checks,
                   "--max-examples", str(args.max_examples), *args.extra]
            env = dict(os.environ, SCHEMATHESIS_HOOKS=__file__, CELLCTL_URL=daemon.url, CELLCTL_TOKEN=daemon.token)
            return subprocess.call(cmd, env=env)
        finally:
            daemon.terminate()
            daemon.log.close()


if __name__ == "__main__":
    sys.exit(main())
