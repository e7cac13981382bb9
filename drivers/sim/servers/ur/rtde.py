"""The RTDE wire format (port 30004) as a controller speaks it: messages, variable types, recipes.

Every message is a big-endian header `>HB` (size including the 3 header bytes, type)
followed by its payload. A client negotiates the protocol version (V), asks the
controller version (v), sets up output recipes (O: frequency + comma-separated names,
answered with a recipe id + the comma-separated types) and input recipes (I: names,
answered the same way), then starts (S) the data stream: data packages (U) carry a
recipe id followed by the recipe's fields packed in order.

The variable tables below follow UR's RTDE guide (PolyScope 5.x). An unknown name is
answered `NOT_FOUND`; an input register that another connection already writes is
answered `IN_USE`, as a controller does.
"""

from __future__ import annotations

import functools
import socket
import struct
from dataclasses import dataclass

HEADER = struct.Struct(">HB")

# message types
REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
CONTROL_PACKAGE_START = ord("S")
CONTROL_PACKAGE_PAUSE = ord("P")
MESSAGE_TYPES = {REQUEST_PROTOCOL_VERSION, GET_URCONTROL_VERSION, TEXT_MESSAGE, DATA_PACKAGE,
                 CONTROL_PACKAGE_SETUP_OUTPUTS, CONTROL_PACKAGE_SETUP_INPUTS, CONTROL_PACKAGE_START,
                 CONTROL_PACKAGE_PAUSE}

# field type -> struct code (and the number of values it carries)
TYPE_CODES: dict[str, tuple[str, int]] = {
    "BOOL": ("?", 1),
    "UINT8": ("B", 1),
    "UINT32": ("I", 1),
    "UINT64": ("Q", 1),
    "INT32": ("i", 1),
    "DOUBLE": ("d", 1),
    "VECTOR3D": ("3d", 3),
    "VECTOR6D": ("6d", 6),
    "VECTOR6INT32": ("6i", 6),
    "VECTOR6UINT32": ("6I", 6),
}

_V6 = "VECTOR6D"
OUTPUT_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE",
    **{name: _V6 for name in (
        "target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q", "actual_qd",
        "actual_current", "actual_current_window", "actual_current_as_torque", "joint_control_output",
        "actual_TCP_pose", "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose", "target_TCP_speed",
        "joint_temperatures", "actual_joint_voltage", "ft_raw_wrench", "payload_inertia",
        "joint_position_deviation_ratio", "target_current_window")},
    "actual_digital_input_bits": "UINT64",
    "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE",
    "actual_digital_output_bits": "UINT64",
    "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE",
    "euromap67_input_bits": "UINT32",
    "euromap67_output_bits": "UINT32",
    "euromap67_24V_voltage": "DOUBLE",
    "euromap67_24V_current": "DOUBLE",
    "tool_mode": "UINT32",
    "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE",
    "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32",
    "tool_output_current": "DOUBLE",
    "tool_temperature": "DOUBLE",
    "tcp_force_scalar": "DOUBLE",
    "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "tool_output_mode": "UINT8",
    "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8",
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "script_control_line": "UINT32",
    "collision_detection_ratio": "DOUBLE",
    "time_scale_source": "INT32",
    **{f"output_bit_register_{i}": "BOOL" for i in range(64, 128)},
    **{f"output_int_register_{i}": "INT32" for i in range(48)},
    **{f"output_double_register_{i}": "DOUBLE" for i in range(48)},
    # inputs can be read back as outputs
    **{f"input_bit_register_{i}": "BOOL" for i in range(64, 128)},
    **{f"input_int_register_{i}": "INT32" for i in range(48)},
    **{f"input_double_register_{i}": "DOUBLE" for i in range(48)},
}

INPUT_TYPES: dict[str, str] = {
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": _V6,
    **{f"input_bit_register_{i}": "BOOL" for i in range(64, 128)},
    **{f"input_int_register_{i}": "INT32" for i in range(48)},
    **{f"input_double_register_{i}": "DOUBLE" for i in range(48)},
}


class ProtocolError(Exception):
    """A frame that breaks the RTDE format; the message says what was wrong and what was expected."""


@dataclass(frozen=True)
class Recipe:
    """An output or input recipe: names, their types and the struct that packs them after the id byte."""

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]

    @property
    def valid(self) -> bool:
        return all(t in TYPE_CODES for t in self.types)

    @functools.cached_property
    def layout(self) -> struct.Struct:
        return struct.Struct(">B" + "".join(TYPE_CODES[t][0] for t in self.types))

    def pack(self, values: dict) -> bytes:
        """Payload of a data package: the id, then every field from `values` (vectors as sequences)."""
        flat: list = []
        for name, kind in zip(self.names, self.types):
            value = values[name]
            if TYPE_CODES[kind][1] == 1:
                flat.append(value)
            else:
                flat.extend(value)
        return self.layout.pack(self.recipe_id, *flat)

    def unpack(self, payload: bytes) -> dict:
        """Field values of a data package for this recipe (the id byte included in `payload`)."""
        layout = self.layout
        if len(payload) != layout.size:
            raise ProtocolError(
                f"data package for recipe {self.recipe_id} has {len(payload)} bytes, expected {layout.size} "
                f"({', '.join(self.names)})"
            )
        flat = layout.unpack(payload)[1:]
        values, i = {}, 0
        for name, kind in zip(self.names, self.types):
            n = TYPE_CODES[kind][1]
            values[name] = flat[i] if n == 1 else tuple(flat[i:i + n])
            i += n
        return values


def parse_names(text: bytes) -> list[str]:
    """Comma-separated variable names; clients (ur_rtde) end the list with a comma."""
    try:
        decoded = text.decode("ascii")
    except UnicodeDecodeError as exc:
        raise ProtocolError(f"variable names are not ASCII: {text[:40]!r}") from exc
    return [n.strip() for n in decoded.split(",") if n.strip()]


def frame(message_type: int, payload: bytes = b"") -> bytes:
    size = HEADER.size + len(payload)
    if size > 0xFFFF:
        raise ProtocolError(f"message of {size} bytes exceeds the 65535-byte limit of the size field")
    return HEADER.pack(size, message_type) + payload


def recv_exact(sock: socket.socket, n: int) -> bytes:
    """Exactly n bytes; ConnectionError if the peer closed, socket.timeout if it went quiet."""
    chunks, remaining = [], n
    while remaining:
        chunk = sock.recv(remaining)
        if not chunk:
            raise ConnectionError("peer closed the connection")
        chunks.append(chunk)
        remaining -= len(chunk)
    return b"".join(chunks)


def read_message(sock: socket.socket) -> tuple[int, bytes]:
    """One framed message (type, payload); a malformed header is a ProtocolError."""
    size, kind = HEADER.unpack(recv_exact(sock, HEADER.size))
    if size < HEADER.size:
        raise ProtocolError(f"message size {size} is below the 3-byte header")
    if kind not in MESSAGE_TYPES:
        raise ProtocolError(f"unknown message type {kind} ({chr(kind)!r}); expected one of V v M U O I S P")
    return kind, recv_exact(sock, size - HEADER.size)
