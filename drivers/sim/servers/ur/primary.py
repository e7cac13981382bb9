"""The primary (30001) and secondary (30002) client interfaces: robot state packages at 10 Hz, URScript in.

On connect a client gets the version message, then a robot state message every 100 ms; both ports take
URScript the way the script port (30003) does (a complete `def|sec name(): ... end` program replaces
the running one). The primary interface also carries other robot messages (texts, errors, key messages);
this simulator sends none, so both ports send the same bytes. Formats follow UR's "Primary and Secondary
Interfaces" guide (e-Series software 5.x), checked against a robot state message a URSim 5.8 UR5e sent
(the sizes below are that robot's): all big-endian.

- Every message: int32 size (including these 5 bytes), uint8 type: 16 robot state, 20 robot message.
- Version message (type 20): uint64 timestamp, int8 source (-2: the controller), uint8 robot message type
  (3: version), int8 project name length, the name ("URControl"), uint8 major, uint8 minor, int32 bugfix,
  int32 build, then the build date (text to the end).
- Robot state (type 16): sub-packages, each int32 size (including its 5-byte header), uint8 type:
  0 robot mode data (47 bytes), 1 joint data (251), 4 cartesian info (101), 5 kinematics info (225),
  3 masterboard data (75), 2 tool data (37), 6 configuration data (445), in the order a UR sends them.
  A real controller adds packages this simulator leaves out (calibration, force mode, additional info,
  safety data, tool communication, tool mode): clients skip unknown types by their size.

Joint angles are the UR5e's of kinematics.py; the cartesian info's TCP pose is the one RTDE reports, and
kinematics and configuration data carry the UR5e's nominal DH table (uncalibrated: checksums all ones,
as URSim reports them).
"""

from __future__ import annotations

import math
import struct

from geometry.ur import UR5E_LIMITS_RAD

from drivers.sim.servers.ur.controller import PAUSED, PLAYING, PROTECTIVE_STOP, RUNNING, Controller

PORTS = {"primary": 30001, "secondary": 30002}
PERIOD_S = 0.1  # 10 Hz, on both interfaces

ROBOT_STATE, ROBOT_MESSAGE = 16, 20
VERSION_MESSAGE = 3
SOURCE_CONTROLLER = -2
ROBOT_MODE_DATA, JOINT_DATA, TOOL_DATA, MASTERBOARD_DATA, CARTESIAN_INFO, KINEMATICS_INFO, CONFIGURATION_DATA = (
    0, 1, 2, 3, 4, 5, 6)
JOINT_RUNNING, JOINT_POWER_OFF = 253, 236
PROJECT_NAME = "URControl"
BUILD_DATE = "01-01-2024, 00:00:00"
UNCALIBRATED_CHECKSUM = 0xFFFFFFFF
# configuration data: the UR5e's as a URSim 5.8 UR5e reports them
JOINT_MAX_SPEED_RAD_S, JOINT_MAX_ACCELERATION_RAD_S2 = math.pi + 0.2, 40.0
DEFAULTS = (1.0471975511965976, 1.3962634015954636, 0.25, 1.2, 0.25)  # v, a joint; v, a tool; blend radius
MASTERBOARD_VERSION, CONTROLLER_BOX_TYPE, ROBOT_TYPE_UR5, ROBOT_SUB_TYPE = 6, 4, 1, 3

_ROBOT_MODE = struct.Struct(">Q???????BBdddB")
_JOINT = struct.Struct(">dddffffB")
_TOOL = struct.Struct(">bbddfBffB")
_MASTERBOARD = struct.Struct(">IIbbddbbddffffB??IB?B")
_CARTESIAN = struct.Struct(">12d")
_KINEMATICS = struct.Struct(">6I24dI")
_CONFIGURATION = struct.Struct(">12d12d5d24d4i")


def frame(kind: int, body: bytes) -> bytes:
    """A message or a sub-package: int32 size (these 5 bytes included), uint8 type, the body."""
    return struct.pack(">iB", 5 + len(body), kind) + body


def version_message(version, timestamp: int = 0) -> bytes:
    """The first message on both interfaces: the controller's version (major, minor, bugfix, build)."""
    major, minor, bugfix, build = (int(v) for v in version)
    name = PROJECT_NAME.encode()
    body = (struct.pack(">QbBb", timestamp, SOURCE_CONTROLLER, VERSION_MESSAGE, len(name)) + name
            + struct.pack(">BBii", major, minor, bugfix, build) + BUILD_DATE.encode())
    return frame(ROBOT_MESSAGE, body)


def robot_state_message(c: Controller, timestamp_us: int) -> bytes:
    """One robot state message for the controller's present state (`timestamp_us`: since it started)."""
    with c.lock:
        actual, target = c.actual_flange(), c.target_flange
        robot_mode, safety_mode, runtime = c.robot_mode, c.safety_mode, c.runtime_state
        tcp_offset = tuple(float(v) for v in c.tcp)
        moving = c.script is not None and c.script._busy()
    q, q_target = c.joints(actual), c.joints(target)
    running = robot_mode == RUNNING
    powered = robot_mode in (4, 5, RUNNING)
    joint_mode = JOINT_RUNNING if running else JOINT_POWER_OFF
    dh = c.kinematics.dh
    a = tuple(row[0] for row in dh)
    d = tuple(row[1] for row in dh)
    alpha = tuple(row[2] for row in dh)
    parts = [
        frame(ROBOT_MODE_DATA, _ROBOT_MODE.pack(
            timestamp_us, True, True, powered, False, safety_mode == PROTECTIVE_STOP, runtime == PLAYING,
            runtime == PAUSED, robot_mode, 0, 1.0, 1.0, 1.0, 0)),
        frame(JOINT_DATA, b"".join(
            _JOINT.pack(q[i], q_target[i], 0.0, 0.0, 47.9 if powered else 0.0, 32.0, 0.0, joint_mode)
            for i in range(6))),
        frame(CARTESIAN_INFO, _CARTESIAN.pack(*c.tcp_pose(actual), *tcp_offset)),
        frame(KINEMATICS_INFO, _KINEMATICS.pack(*(UNCALIBRATED_CHECKSUM,) * 6, *(0.0,) * 6, *a, *d, *alpha,
                                                      0)),
        frame(MASTERBOARD_DATA, _MASTERBOARD.pack(
            0, 0, 0, 0, 0.0, 0.0, 0, 0, 0.0, 0.0, 35.0, 48.0 if powered else 0.0, 0.6 if moving else 0.3, 0.0,
            safety_mode, False, False, 0, 0, False, 0)),
        frame(TOOL_DATA, _TOOL.pack(0, 0, 0.0, 0.0, 24.0 if powered else 0.0, 0, 0.0, 30.0, joint_mode)),
        frame(CONFIGURATION_DATA, _CONFIGURATION.pack(
            *(v for lo_hi in UR5E_LIMITS_RAD for v in lo_hi),
            *(JOINT_MAX_SPEED_RAD_S, JOINT_MAX_ACCELERATION_RAD_S2) * 6, *DEFAULTS, *a, *d, *alpha, *(0.0,) * 6,
            MASTERBOARD_VERSION, CONTROLLER_BOX_TYPE, ROBOT_TYPE_UR5, ROBOT_SUB_TYPE)),
    ]
    return frame(ROBOT_STATE, b"".join(parts))


def parse(data: bytes) -> tuple[list[tuple[int, bytes]], bytes]:
    """Split a byte stream into complete messages (type, body) and the incomplete rest (for tests and tools)."""
    out = []
    while len(data) >= 5:
        size, kind = struct.unpack(">iB", data[:5])
        if size < 5:
            raise ValueError(f"message size {size} is below the 5-byte header")
        if len(data) < size:
            break
        out.append((kind, data[5:size]))
        data = data[size:]
    return out, data


def sub_packages(body: bytes) -> dict[int, bytes]:
    """A robot state message's sub-packages by type (each body without its 5-byte header)."""
    out, i = {}, 0
    while i < len(body):
        size, kind = struct.unpack(">iB", body[i:i + 5])
        if size < 5 or i + size > len(body):
            raise ValueError(f"sub-package of type {kind} at byte {i} has size {size}: broken")
        out[kind] = body[i + 5:i + size]
        i += size
    return out
