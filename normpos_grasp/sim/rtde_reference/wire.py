"""RTDE v2 framing and the variable table of the reference controller.

Written from UR's RTDE guide as summarised in shared/reference/rtde_notes.md: a packet is
`uint16 size (header included) | uint8 type | payload`, big-endian. Every variable has one fixed type; the client
(ur_rtde) decodes with its own table, so these must be UR's.
"""

from __future__ import annotations

import socket
import struct
from collections.abc import Iterable

from normpos_grasp.errors import NormposError

HEADER = struct.Struct(">HB")
# packet types (ASCII letters)
PROTOCOL_VERSION, CONTROL_VERSION, TEXT, DATA = b"V"[0], b"v"[0], b"M"[0], b"U"[0]
SETUP_OUTPUTS, SETUP_INPUTS, START, PAUSE = b"O"[0], b"I"[0], b"S"[0], b"P"[0]

FORMAT = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "ddd",
    "VECTOR6D": "dddddd",
    "VECTOR6INT32": "iiiiii",
    "VECTOR6UINT32": "IIIIII",
}
WIDTH = {name: len(fmt) for name, fmt in FORMAT.items()}


def _names(text: str) -> list[str]:
    return text.split()


def _table() -> tuple[dict[str, str], dict[str, str]]:
    six = "VECTOR6D"
    out: dict[str, str] = dict.fromkeys(
        _names(
            "target_q target_qd target_qdd target_current target_moment actual_q actual_qd actual_current "
            "joint_control_output actual_TCP_pose actual_TCP_speed actual_TCP_force target_TCP_pose "
            "target_TCP_speed joint_temperatures actual_joint_voltage payload_inertia ft_raw_wrench "
            "actual_current_window actual_current_as_torque "
        ),
        six,
    )
    out.update(
        dict.fromkeys(
            _names(
                "timestamp actual_execution_time speed_scaling target_speed_fraction actual_momentum "
                "actual_main_voltage actual_robot_voltage actual_robot_current standard_analog_input0 "
                "standard_analog_input1 standard_analog_output0 standard_analog_output1 io_current "
                "euromap67_24V_voltage euromap67_24V_current tool_analog_input0 tool_analog_input1 "
                "tool_output_current tool_temperature tcp_force_scalar payload joint_position_deviation_ratio "
                "collision_detection_ratio "
            ),
            "DOUBLE",
        )
    )
    out.update(dict.fromkeys(["robot_mode", "safety_mode", "safety_status", "tool_output_voltage"], "INT32"))
    out.update(
        dict.fromkeys(
            _names(
                "runtime_state robot_status_bits safety_status_bits analog_io_types euromap67_input_bits "
                "euromap67_output_bits tool_mode tool_analog_input_types output_bit_registers0_to_31 "
                "output_bit_registers32_to_63 input_bit_registers0_to_31 input_bit_registers32_to_63 "
                "script_control_line "
            ),
            "UINT32",
        )
    )
    out.update(dict.fromkeys(["actual_digital_input_bits", "actual_digital_output_bits"], "UINT64"))
    out.update(
        dict.fromkeys(["actual_tool_accelerometer", "payload_cog", "elbow_position", "elbow_velocity"], "VECTOR3D")
    )
    out["joint_mode"] = "VECTOR6INT32"
    for i in range(48):
        out[f"output_int_register_{i}"] = out[f"input_int_register_{i}"] = "INT32"
        out[f"output_double_register_{i}"] = out[f"input_double_register_{i}"] = "DOUBLE"
    for i in range(64, 128):
        out[f"output_bit_register_{i}"] = out[f"input_bit_register_{i}"] = "BOOL"
    inputs: dict[str, str] = {"speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE"}
    for bank in ("standard_digital_output", "configurable_digital_output", "tool_digital_output"):
        inputs[bank + "_mask"] = inputs[bank] = "UINT8"
    inputs.update(
        {
            "standard_analog_output_mask": "UINT8",
            "standard_analog_output_type": "UINT8",
            "standard_analog_output_0": "DOUBLE",
            "standard_analog_output_1": "DOUBLE",
            "input_bit_registers0_to_31": "UINT32",
            "input_bit_registers32_to_63": "UINT32",
            "external_force_torque": six,
        }
    )
    for i in range(48):
        inputs[f"input_int_register_{i}"] = "INT32"
        inputs[f"input_double_register_{i}"] = "DOUBLE"
    for i in range(64, 128):
        inputs[f"input_bit_register_{i}"] = "BOOL"
    return out, inputs


OUTPUT_TYPES, INPUT_TYPES = _table()


class WireError(NormposError):
    """A malformed RTDE packet from a client."""


def packet(kind: int, payload: bytes = b"") -> bytes:
    return HEADER.pack(HEADER.size + len(payload), kind) + payload


def read_packet(sock: socket.socket) -> tuple[int, bytes]:
    """One packet (type, payload); EOFError when the peer closed."""
    head = _read_exact(sock, HEADER.size)
    size, kind = HEADER.unpack(head)
    if size < HEADER.size:
        raise WireError(f"RTDE packet size {size} is below its header size")
    return kind, _read_exact(sock, size - HEADER.size)


def _read_exact(sock: socket.socket, n: int) -> bytes:
    chunks, got = [], 0
    while got < n:
        part = sock.recv(n - got)
        if not part:
            raise EOFError("peer closed")
        chunks.append(part)
        got += len(part)
    return b"".join(chunks)


def recipe_struct(types: Iterable[str]) -> struct.Struct:
    return struct.Struct(">" + "".join(FORMAT[t] for t in types))


def split_values(types: list[str], flat: tuple[object, ...]) -> list[object]:
    """Flat unpacked values -> one value per variable (vectors as tuples)."""
    out, i = [], 0
    for t in types:
        w = WIDTH[t]
        out.append(flat[i] if w == 1 else tuple(flat[i : i + w]))
        i += w
    return out
