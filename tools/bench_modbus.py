"""Round trip of a gripper status read over Modbus on loopback, against the protocol simulators.

Three links:
- Modbus TCP: the VGC10 simulator, FC03 read of the two actual-vacuum registers;
- RTU over TCP: the EPick simulator, FC04 read of the three status registers;
- RTU on a socat pty pair (115200 8N1): the same EPick read.

It prints the median and 99th percentile of the bare link round trip (no pacing),
and the period of the EPick driver's `status()` in a loop, which the driver paces
to one request per 5 ms as the gripper needs. By default each simulator runs in
its own process (no GIL shared with the client); --in-process runs it in a thread.

    .venv/bin/python tools/bench_modbus.py [--reads 2000] [--in-process]
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import yaml

from drivers.grippers.epick import EPickGripper
from drivers.grippers.modbus_link import LinkConfig, ModbusLink
from drivers.interfaces import ConnectionLost
from drivers.sim.micro.config import SimWorldConfig
from drivers.sim.servers import free_ports


def _world_config() -> SimWorldConfig:
    return SimWorldConfig(**yaml.safe_load((ROOT / "config" / "sim-microcell.yaml").read_text())["sim"])


def _serve(kind: str, port: int, serial_port: str | None, stop) -> None:
    if kind == "vgc10":
        from drivers.sim.servers.vgc10 import serve
        serve(_world_config(), port=port, stop=stop)
    else:
        from drivers.sim.servers.epick import serve
        serve(_world_config(), port=port, serial_port=serial_port, stop=stop)


@contextlib.contextmanager
def _serving(kind: str, port: int, serial_port: str | None, in_process: bool):
    """A simulator running (in a thread or a process) for the duration of the block."""
    if in_process:
        stop = threading.Event()
        worker = threading.Thread(target=_serve, args=(kind, port, serial_port, stop), daemon=True)
    else:
        stop = multiprocessing.Event()
        worker = multiprocessing.Process(target=_serve, args=(kind, port, serial_port, stop), daemon=True)
    worker.start()
    try:
        yield
    finally:
        stop.set()
        worker.join(10)


def _open(config: LinkConfig, within_s: float = 10.0) -> ModbusLink:
    """Open the link once the simulator answers (it starts in the background)."""
    deadline = time.monotonic() + within_s
    while True:
        link = ModbusLink("bench", config)
        try:
            link.open()
            return link
        except ConnectionLost:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def _round_trips(link: ModbusLink, address: int, count: int, function: int, reads: int) -> list[float]:
    for _ in range(20):  # warm up
        link.read(address, count, function)
    times = []
    for _ in range(reads):
        start = time.perf_counter()
        link.read(address, count, function)
        times.append(time.perf_counter() - start)
    return times


def _report(label: str, times: list[float]) -> None:
    ms = sorted(t * 1e3 for t in times)
    p99 = ms[min(len(ms) - 1, round(0.99 * (len(ms) - 1)))]
    print(f"{label:<44} median {statistics.median(ms):6.3f} ms   p99 {p99:6.3f} ms   ({len(ms)} reads)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reads", type=int, default=2000)
    parser.add_argument("--in-process", action="store_true", help="run the simulators in threads of this process")
    args = parser.parse_args()
    where = "thread" if args.in_process else "process"
    print(f"simulators in a separate {where}; pymodbus sync clients; loopback")

    port, = free_ports()
    with _serving("vgc10", port, None, args.in_process):
        link = _open(LinkConfig(kind="tcp", device_id=65, timeout_s=1.0, host="127.0.0.1", port=port))
        _report("Modbus TCP, VGC10 vacuum (FC03, 2 regs)", _round_trips(link, 258, 2, 3, args.reads))
        link.close()

    port, = free_ports()
    with _serving("epick", port, None, args.in_process):
        link = _open(LinkConfig(kind="rtu-over-tcp", device_id=9, timeout_s=1.0, host="127.0.0.1", port=port))
        _report("RTU over TCP, EPick status (FC04, 3 regs)", _round_trips(link, 0x07D0, 3, 4, args.reads))
        link.close()
        gripper = EPickGripper.create("epick", {"transport": "tcp", "port": port, "timeout_s": 1.0})
        gripper.connect()
        start = time.perf_counter()
        n = min(args.reads, 400)
        for _ in range(n):
            gripper.status()
        print(f"{'  EPick driver status() period (5 ms pacing)':<44} mean   {(time.perf_counter() - start) / n * 1e3:6.3f} ms")
        gripper.close()

    if shutil.which("socat") is None:
        print("RTU on a pty pair: skipped (socat is not installed)")
        return
    folder = tempfile.mkdtemp(prefix="bench-modbus-")
    a, b = os.path.join(folder, "ttyA"), os.path.join(folder, "ttyB")
    socat = subprocess.Popen(["socat", "-d", "-d", f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 5
        while not (os.path.exists(a) and os.path.exists(b)) and time.monotonic() < deadline:
            time.sleep(0.01)
        with _serving("epick", 0, b, args.in_process):
            config = LinkConfig(kind="serial", device_id=9, timeout_s=0.5, serial_port=a)
            link = _open(config)
            # the server may still be opening its end: the first reads can go unanswered
            deadline = time.monotonic() + 10
            while True:
                try:
                    link.read(0x07D0, 3, 4)
                    break
                except ConnectionLost:
                    if time.monotonic() > deadline:
                        raise
                    link = _open(config)
            _report("RTU on a pty pair, EPick status (FC04, 3 regs)", _round_trips(link, 0x07D0, 3, 4, args.reads))
            link.close()
    finally:
        socat.terminate()
        socat.wait(5)
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
