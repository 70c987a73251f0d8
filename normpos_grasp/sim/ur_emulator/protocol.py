"""RTDE protocol v2 wire format: packet framing, the variable type table and value packing.

Packets are `uint16 size (incl. 3-byte header) | uint8 type | payload`, big-endian. ur_rtde decodes output data
with its own type table, so the types here follow UR's RTDE guide exactly.
"""

from __future__ import annotations

import socket
import struct
from collections.abc import Sequence
from typing import Any

from normpos_grasp.errors import NormposError

REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
CONTROL_PACKAGE_START = ord("S")
CONTROL_PACKAGE_PAUSE = ord("P")

# type name -> struct format (without byte order)
TYPE_FORMATS: dict[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}

_V6 = "VECTOR6D"
_OUTPUT_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": _V6,
    "target_qd": _V6,
    "target_qdd": _V6,
    "target_current": _V6,
    "target_moment": _V6,
    "actual_q": _V6,
    "actual_qd": _V6,
    "actual_qdd": _V6,
    "actual_current": _V6,
    "actual_current_as_torque": _V6,
    "actual_moment": _V6,
    "joint_control_output": _V6,
    "actual_TCP_pose": _V6,
    "actual_TCP_speed": _V6,
    "actual_TCP_force": _V6,
    "target_TCP_pose": _V6,
    "target_TCP_speed": _V6,
    "actual_digital_input_bits": "UINT64",
    "joint_temperatures": _V6,
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
    "actual_joint_voltage": _V6,
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
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "payload_inertia": _V6,
    "script_control_line": "UINT32",
    "ft_raw_wrench": _V6,
    "joint_position_deviation_ratio": "DOUBLE",
    "collision_detection_ratio": "DOUBLE",
    "time_scale_source": "UINT32",
}
_INPUT_TYPES: dict[str, str] = {
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
}
for _i in range(48):
    _OUTPUT_TYPES[f"output_int_register_{_i}"] = "INT32"
    _OUTPUT_TYPES[f"output_double_register_{_i}"] = "DOUBLE"
    _OUTPUT_TYPES[f"input_int_register_{_i}"] = "INT32"
    _OUTPUT_TYPES[f"input_double_register_{_i}"] = "DOUBLE"
    _INPUT_TYPES[f"input_int_register_{_i}"] = "INT32"
    _INPUT_TYPES[f"input_double_register_{_i}"] = "DOUBLE"
for _i in range(64, 128):
    _OUTPUT_TYPES[f"output_bit_register_{_i}"] = "BOOL"
    _OUTPUT_TYPES[f"input_bit_register_{_i}"] = "BOOL"
    _INPUT_TYPES[f"input_bit_register_{_i}"] = "BOOL"

OUTPUT_TYPES: dict[str, str] = dict(_OUTPUT_TYPES)
INPUT_TYPES: dict[str, str] = dict(_INPUT_TYPES)


class ProtocolError(NormposError):
    """A peer sent bytes that do not follow RTDE protocol v2."""


class PeerClosed(NormposError):
    """The peer closed the socket."""


def pack_packet(kind: int, payload: bytes = b"") -> bytes:
    """One RTDE packet: header (size incl. header, type) + payload."""
    return struct.pack(">HB", len(payload) + 3, kind) + payload


def recv_exact(sock: socket.socket, n: int) -> bytes:
    """Read exactly n bytes; raises PeerClosed when the peer closes first."""
    chunks = bytearray()
    while len(chunks) < n:
        chunk = sock.recv(n - len(chunks))
        if not chunk:
            raise PeerClosed(f"peer closed after {len(chunks)} of {n} bytes")
        chunks.extend(chunk)
    return bytes(chunks)


def recv_packet(sock: socket.socket) -> tuple[int, bytes]:
    """(type, payload) of the next packet."""
    size, kind = struct.unpack(">HB", recv_exact(sock, 3))
    if size < 3:
        raise ProtocolError(f"RTDE packet size {size} < 3 (header alone is 3 bytes)")
    return kind, recv_exact(sock, size - 3)


def recipe_struct(types: Sequence[str]) -> struct.Struct:
    """Big-endian struct for a recipe's values (after the recipe id byte)."""
    return struct.Struct(">" + "".join(TYPE_FORMATS[t] for t in types))


def flatten(values: Sequence[Any], types: Sequence[str]) -> list[Any]:
    """Flatten vector values so they fit `recipe_struct(types)`."""
    out: list[Any] = []
    for value, kind in zip(values, types, strict=True):
        if kind.startswith("VECTOR"):
            out.extend(value)
        else:
            out.append(value)
    return out


def unflatten(flat: Sequence[Any], types: Sequence[str]) -> list[Any]:
    """Inverse of `flatten`: group vector components back into tuples."""
    out: list[Any] = []
    i = 0
    for kind in types:
        n = 6 if kind.startswith("VECTOR6") else 3 if kind == "VECTOR3D" else 1
        out.append(tuple(flat[i : i + n]) if n > 1 else flat[i])
        i += n
    return out
