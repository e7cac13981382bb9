"""Independent peers: a client that talks as the public open_abb Python client does, against `cellctl sim abb`;
a stand-in for the stock SERVER.mod / LOGGER.mod, driven by AbbArm."""

from __future__ import annotations

import math
import socket
import threading

import pytest

from geometry.orientation import quaternion_wxyz, tool_down

from drivers.arms.abb import AbbArm
from drivers.interfaces import (
    Pose,
)

from tests.support.abb import (
    LIMITS,
    same_rotation,
    sim_abb_by_hand,
)
from tests.support.wait import eventually

# --- independent peers -------------------------------------------------------------------


class PublicStyleClient:
    """Talks as the public open_abb Python client does (written here from its behaviour): each request
    one send() of its text, each reply one recv(4096), then split() and float() on every token."""

    def __init__(self, host: str, port: int):
        self.sock = socket.create_connection((host, port), timeout=5.0)
        self.raw: list[bytes] = []

    def send(self, message: str) -> bytes:
        self.sock.send(message.encode("ascii"))
        data = self.sock.recv(4096)
        self.raw.append(data)
        return data

    def numbers(self, message: str) -> list[float]:
        return [float(token) for token in self.send(message).split()]

    @staticmethod
    def frame(xyz_mm, quaternion) -> str:
        """The client's number format: mm with one decimal, quaternions with five, signed, zero-padded."""
        return " ".join([format(v, "+08.1f") for v in xyz_mm] + [format(v, "+08.5f") for v in quaternion])

    def close(self) -> None:
        self.sock.send(b"99 #")  # the public client does not wait for this reply
        self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()





def test_a_public_style_open_abb_client_drives_cellctl_sim_abb():
    """`cellctl sim abb` as started by hand answers in the stock format: every token of every reply
    float()s, 98 splits on '*', nothing ends in '#'."""
    with sim_abb_by_hand() as port:
        client = PublicStyleClient("127.0.0.1", port)
        identity = client.frame((0, 0, 0), (1, 0, 0, 0))
        assert client.numbers("00 #") == [0, 1]
        assert client.numbers(f"06 {identity} #") == [6, 1]
        assert client.numbers(f"07 {identity} #") == [7, 1]
        assert client.numbers("08 +0100.0 +0050.0 +0050.0 +0050.0 #") == [8, 1]
        assert client.numbers("09 0 +01.0000 +01.0000 +00.1000 #") == [9, 1]  # z1
        q90 = quaternion_wxyz(tool_down(math.radians(90)))
        assert client.numbers(f"01 {client.frame((50, 40, 10), q90)} #") == [1, 1]
        r = client.numbers("03 #")
        assert r[:2] == [3, 1] and len(r) == 9
        assert r[2:5] == pytest.approx([50, 40, 10], abs=0.051)
        assert same_rotation(r[5:9], q90, 1e-4)
        j = client.numbers("04 #")
        assert j[:2] == [4, 1] and j[2:8] == pytest.approx([50, 40, 10, 90, 0, 0], abs=0.051)
        assert client.numbers("31 #") == [31, 1]
        q0 = quaternion_wxyz(tool_down(0.0))
        for x in (45, 55):
            assert client.numbers(f"30 {client.frame((x, 35, 10), q0)} #") == [30, 1]
        assert int(float(client.send("32 #").split()[2])) == 2
        assert client.numbers("33 #") == [33, 1]
        assert client.numbers("03 #")[2:5] == pytest.approx([55, 35, 10], abs=0.051)
        info = client.send("98 #")[5:].split(b"*")
        assert info == [b"SIM-0001", b"6.99.0 cellctl-sim", b"cellctl 4-axis micro cell"]
        client.close()
        assert not any(b"#" in reply for reply in client.raw), client.raw
        again = PublicStyleClient("127.0.0.1", port)  # the server takes the next client
        assert again.numbers("00 #") == [0, 1]
        again.close()


class StockOpenAbbServer:
    """A stand-in for the public SERVER.mod and LOGGER.mod as they look on the wire (not their code):
    replies "<code> <ok> <data>" with no terminator, one send each, numbers with few decimals (2 for mm
    and degrees, 3 for quaternions here); logger lines "# 0 ..." with no newline. Knows no status 2 or 3."""

    def __init__(self):
        self.pose = [300.0, 0.0, 400.0, 0.0, 0.0, 1.0, 0.0]
        self.codes: list[int] = []
        self._stop = threading.Event()
        self._listeners = []
        for _ in range(2):
            sock = socket.socket()
            sock.bind(("127.0.0.1", 0))
            sock.listen(1)
            sock.settimeout(5.0)
            self._listeners.append(sock)
        self.motion_port, self.logger_port = (s.getsockname()[1] for s in self._listeners)
        self._threads = [threading.Thread(target=self._motion, name="stock-abb-motion"),
                         threading.Thread(target=self._logger, name="stock-abb-logger")]
        for thread in self._threads:
            thread.start()

    def _cartesian(self) -> str:
        return " ".join([f"{v:.2f}" for v in self.pose[:3]] + [f"{v:.3f}" for v in self.pose[3:]])

    def _motion(self):
        try:
            client, _ = self._listeners[0].accept()
        except OSError:
            return
        with client:
            buffer = b""
            while True:
                while b"#" not in buffer:
                    chunk = client.recv(1024)
                    if not chunk:
                        return
                    buffer += chunk
                message, _, buffer = buffer.partition(b"#")
                tokens = message.split()
                code, params = int(tokens[0]), [float(t) for t in tokens[1:]]
                self.codes.append(code)
                data = ""
                if code == 1 and len(params) == 7:
                    self.pose = params
                elif code == 3:
                    data = self._cartesian()
                elif code == 4:
                    data = "10.00 -20.00 30.00 0.00 90.00 0.00"
                elif code == 98:
                    data = "120-505050*6.10.1*IRB 120-3/0.6"
                client.sendall(f"{code} 1 {data}".encode())
                if code == 99:
                    return

    def _logger(self):
        try:
            client, _ = self._listeners[1].accept()
        except OSError:
            return
        with client:
            t = 0.0
            while not self._stop.wait(0.01):  # the logger's period
                t += 0.01
                try:
                    client.sendall(f"# 0 2026-11-22 10:00:00 {t:.2f} {self._cartesian()}".encode())
                except OSError:
                    return

    def close(self):
        self._stop.set()
        for sock in self._listeners:
            sock.close()
        for thread in self._threads:
            thread.join(timeout=5.0)


def test_abb_arm_drives_a_stock_open_abb_server():
    stock = StockOpenAbbServer()
    try:
        arm = AbbArm.create("abb", {"host": "127.0.0.1", "motion_port": stock.motion_port,
                                    "logger_port": stock.logger_port, "limits": LIMITS,
                                    "reply_timeout_s": 2.0, "move_timeout_s": 2.0})
        arm.connect()
        target = Pose(0.050, 0.040, 0.010, math.radians(90))
        arm.move_linear(target)
        pose = arm.pose()
        assert math.dist(pose.xyz, target.xyz) < 1e-5  # 2 decimals of a mm
        assert pose.alpha == pytest.approx(target.alpha, abs=2e-3)  # 3 decimals of a quaternion
        assert arm.joints().positions[4] == pytest.approx(math.radians(90))
        assert arm.robot_info().robot_type == "IRB 120-3/0.6"
        # the logger's lines have no newline: each ends at the next '#'
        eventually(lambda: (cartesian := arm.logged()[0]) is not None and cartesian.values[:3] == (50.0, 40.0, 10.0),
                   timeout=3.0, every=0.01, what="the logged pose at (50, 40, 10)")
        arm.close()
    finally:
        stock.close()
    assert stock.codes == [0, 6, 7, 8, 9, 1, 3, 4, 98, 99]
