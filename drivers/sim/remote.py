"""Share one simulated arm between processes: the world's owner serves it, a protocol simulator drives it.

Why: a protocol simulator for a client library that holds the GIL (ur_rtde's
constructors do) must run in its own process, yet the cameras that watch the arm live
in the process that owns the World. So the owner exposes its SimArm on loopback and
the simulator process moves that very arm:

    # the process that owns the World (a test, or `cellctl` running a sim cell)
    host = ArmHost(sim_arm)                         # listens on 127.0.0.1, random port and key
    start the simulator with host.address and host.authkey (e.g. `python -m drivers.sim.servers.ur
    --arm-address 127.0.0.1:PORT` with the key in the environment variable CELLCTL_SIM_AUTHKEY)
    ...
    host.close()

    # the simulator process
    arm = RemoteArm(address, authkey)               # same calls as the SimArm: move_linear, pose, stop
    arm.move_linear(Pose(...))

The mechanism is drivers/rpc.py (ObjectHost, ObjectClient): pickled tuples over
`multiprocessing.connection` with an HMAC authkey, on loopback only. Every call has a time-out; a host that went away is ConnectionLost.
Typed driver errors raised by the arm (MotionStopped, ProtectiveStop, MotionRejected,
ConnectionLost …) come back as the same types.

The GIL trap: the host answers from a thread of the owner's process, which needs that
process's GIL. Call the remote arm only when the owner is known to release the GIL
(inside ur_rtde's moveL/moveJ, which release it, or a plain Python wait) — never while
it may be inside a ur_rtde constructor. The UR simulator therefore reads the pose once
at start and then only after the moves it executes.
"""

from __future__ import annotations

from drivers.interfaces import DeviceError, JointState, Pose
from drivers.rpc import ObjectClient, ObjectHost, parse_address
from drivers.sim.base import MotionTimed

_CALLS = {"move_linear", "move_joints", "pose", "joints", "stop", "wall_seconds"}


class ArmHost(ObjectHost):
    """Serves an arm (normally the World's SimArm) to other processes until `close()`."""

    typed_errors = (DeviceError,)  # anything else is the arm's bug: a DeviceError naming it

    def __init__(self, arm, host: str = "127.0.0.1", port: int = 0, authkey: bytes | None = None):
        self.arm = arm
        super().__init__(arm, _CALLS, host=host, port=port, authkey=authkey, name="arm-host")

    def dispatch(self, name: str, args: tuple):
        if name == "wall_seconds":
            return self.wall_seconds(*args)
        return getattr(self.arm, name)(*args)

    def wall_seconds(self, start: Pose, target: Pose) -> float:
        """Wall time a move will take (a simulator shows the arm moving meanwhile); 0 if moves are instant."""
        return self.arm.wall_seconds(start, target) if isinstance(self.arm, MotionTimed) else 0.0


class RemoteArm:
    """Client side of ArmHost: the arm's calls, each with a time-out. Thread-safe; stop() never waits for a move."""

    def __init__(self, address, authkey: bytes, timeout_s: float = 5.0, move_timeout_s: float = 300.0):
        self.address = parse_address(address)
        self.authkey = authkey
        self.timeout_s = timeout_s
        self.move_timeout_s = move_timeout_s
        self._client = ObjectClient(self.address, authkey, timeout_s, what="simulated arm")

    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        self._client.request("move_linear", target, speed, timeout_s=self.move_timeout_s)

    def move_joints(self, joints: JointState, speed: float | None = None) -> None:
        self._client.request("move_joints", joints, speed, timeout_s=self.move_timeout_s)

    def pose(self) -> Pose:
        return self._client.request("pose")

    def joints(self) -> JointState:
        return self._client.request("joints")

    def stop(self) -> None:
        self._client.request("stop")

    def wall_seconds(self, start: Pose, target: Pose) -> float:
        return self._client.request("wall_seconds", start, target)

    def close(self) -> None:
        self._client.close()
