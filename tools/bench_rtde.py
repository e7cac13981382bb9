"""RTDE receive benchmark: is the 500 Hz stream complete and regular over N seconds?

Clients read the same controller (the UR simulator, started here in its
own process, or a real robot with --no-sim):

- `ur_rtde`: ur_rtde's RTDEReceiveInterface, polled for new controller timestamps;
- `raw`: a plain socket RTDE client (handshake V/v/O/S, then every data package);
- `recording`: ur_rtde's `startFileRecording` CSV of the controller timestamp. Measured here
  (2026-11-22, ur-rtde 1.6.5) it is not a packet log: ur_rtde writes it from a thread of its own
  on a 500 Hz timer, so over 10 s it held 39 repeated and 42 skipped timestamps while the raw
  client, on the same stream, saw all 5000 packets 2.000 ms apart. Like the polled `ur_rtde`
  client, it measures the library's sampling, not the stream.

For each: packets received vs expected (seconds x 500), gaps (controller timestamps more
than 1.5 periods apart), the largest interval between consecutive packets (controller
clock and host arrival), and the arrival jitter (standard deviation of the host-side
intervals). The acceptance figure is "500 Hz with no gaps over 60 s".

    .venv/bin/python tools/bench_rtde.py                   # 60 s each, simulator on 127.0.0.7
    .venv/bin/python tools/bench_rtde.py --seconds 10 --client raw
"""

from __future__ import annotations

import argparse
import socket
import struct
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.sim.servers.ur import SimulatorProcess
from drivers.sim.servers.ur import rtde as wire

PERIOD = 1.0 / 500


def raw_client(host: str, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """(controller timestamps, host arrival times) of every data package for `seconds`."""
    names = ("timestamp", "actual_q", "actual_TCP_pose", "runtime_state", "safety_status_bits")
    with socket.create_connection((host, 30004), timeout=2.0) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

        def request(kind: int, payload: bytes = b"") -> bytes:
            sock.sendall(wire.frame(kind, payload))
            got, reply = wire.read_message(sock)
            if got != kind:
                raise wire.ProtocolError(f"expected the reply to {chr(kind)!r}, got {chr(got)!r}")
            return reply

        if request(wire.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) != b"\x01":
            raise wire.ProtocolError("protocol version 2 refused")
        major = struct.unpack(">IIII", request(wire.GET_URCONTROL_VERSION))[0]
        frequency = 500.0 if major >= 5 else 125.0
        reply = request(wire.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", frequency) + ",".join(names).encode())
        recipe = wire.Recipe(reply[0], names, tuple(reply[1:].decode().split(",")))
        if not recipe.valid:
            raise wire.ProtocolError(f"output recipe refused: {reply[1:].decode()}")
        if request(wire.CONTROL_PACKAGE_START) != b"\x01":
            raise wire.ProtocolError("start refused")
        stamps, arrivals = [], []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            kind, payload = wire.read_message(sock)
            arrivals.append(time.monotonic())
            if kind == wire.DATA_PACKAGE:
                stamps.append(recipe.unpack(payload)["timestamp"])
        sock.sendall(wire.frame(wire.CONTROL_PACKAGE_PAUSE))
    return np.array(stamps), np.array(arrivals)


def ur_rtde_client(host: str, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """New timestamps seen by polling RTDEReceiveInterface (every 0.1 ms) for `seconds`."""
    import rtde_receive

    receive = rtde_receive.RTDEReceiveInterface(host, -1.0, ["timestamp", "actual_q", "actual_TCP_pose"])
    stamps, arrivals = [], []
    last = None
    end = time.monotonic() + seconds
    try:
        while time.monotonic() < end:
            stamp = receive.getTimestamp()
            if stamp != last:
                arrivals.append(time.monotonic())
                stamps.append(stamp)
                last = stamp
            time.sleep(0.0001)
    finally:
        receive.disconnect()
    return np.array(stamps), np.array(arrivals)


def recording_client(host: str, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Every controller timestamp ur_rtde's receive thread recorded for `seconds`."""
    import tempfile

    import rtde_receive

    receive = rtde_receive.RTDEReceiveInterface(host, -1.0, ["timestamp", "actual_q", "actual_TCP_pose"])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "rtde.csv"
        try:
            receive.startFileRecording(str(path), ["timestamp"])
            time.sleep(seconds)
            receive.stopFileRecording()
        finally:
            receive.disconnect()
        stamps = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=1)
    return stamps, stamps.copy()


def report(name: str, stamps: np.ndarray, arrivals: np.ndarray, seconds: float) -> dict:
    expected = round(seconds / PERIOD)
    steps = np.diff(stamps)
    intervals = np.diff(arrivals)
    gaps = steps[steps > 1.5 * PERIOD]
    row = {
        "client": name,
        "received": len(stamps),
        "expected": expected,
        "missing": round(gaps.sum() / PERIOD - len(gaps)) if len(gaps) else 0,
        "gaps": len(gaps),
        "max_step_ms": float(steps.max() * 1e3) if len(steps) else float("nan"),
        "max_interval_ms": float(intervals.max() * 1e3) if len(intervals) else float("nan"),
        "jitter_ms": float(intervals.std() * 1e3) if len(intervals) else float("nan"),
        "p99_interval_ms": float(np.percentile(intervals, 99) * 1e3) if len(intervals) else float("nan"),
    }
    print(f"{name:>8}: received {row['received']} of {row['expected']} expected, {row['gaps']} gaps "
          f"({row['missing']} packets missing by controller timestamp), max controller step "
          f"{row['max_step_ms']:.2f} ms, max arrival interval {row['max_interval_ms']:.2f} ms, "
          f"p99 {row['p99_interval_ms']:.2f} ms, jitter (sd) {row['jitter_ms']:.3f} ms")
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--host", default="127.0.0.7")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--client", choices=("all", "raw", "ur_rtde", "recording"), default="all")
    parser.add_argument("--no-sim", action="store_true", help="measure a controller already at --host")
    args = parser.parse_args()

    sim = None if args.no_sim else SimulatorProcess(args.host, Path(__file__).resolve().parents[1]
                                                    / "config" / "sim-microcell.yaml").start()
    try:
        rows = []
        for name, client in (("raw", raw_client), ("recording", recording_client), ("ur_rtde", ur_rtde_client)):
            if args.client in ("all", name):
                rows.append(report(name, *client(args.host, args.seconds), args.seconds))
    finally:
        if sim is not None:
            code = sim.stop()
            print(f"simulator stopped, exit status {code}")
    return 0 if all(r["gaps"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
