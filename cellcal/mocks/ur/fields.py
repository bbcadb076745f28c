"""The RTDE field table of the UR twin: every output a PolyScope 5.11 controller serves
(UR's RTDE guide, with the guide's types), every input it takes, and where each value
comes from. Stdlib only (it runs in the twin's child process).

Where the values come from:

* from the simulation: ``timestamp`` (controller cycles × 2 ms), ``target_q`` /
  ``actual_q``, ``target_qd`` / ``actual_qd``, ``target_qdd``, ``actual_TCP_pose`` /
  ``target_TCP_pose`` and ``actual_TCP_speed`` / ``target_TCP_speed`` (computed by the
  parent from the joints), the modes and safety words, ``runtime_state``,
  ``robot_status_bits``, ``target_speed_fraction`` (the speed slider input), the digital
  and analog outputs and every register (set through the inputs), and
  ``joint_temperatures``: each joint warming from :data:`COLD_BY_C` below its working
  temperature towards it, with time constant :data:`WARM_TAU_S` of the controller's
  uptime (``timestamp``);
* constant but realistic: currents, moments, voltages, accelerometer,
  forces (``tcp_force_scalar`` is the norm of ``actual_TCP_force``), payload, elbow,
  tool and Euromap words. A target equals its actual (the twin has no tracking error).

Names the guide does not have, and the ones it marks as introduced after 5.11
(:data:`LATER_OUTPUTS`, e.g. ``actual_current_as_torque``, 5.23), are ``NOT_FOUND``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from cellcal.mocks.ur.rtde_codec import CYCLE_S

if TYPE_CHECKING:
    from cellcal.mocks.ur.controller import Controller

_B, _U8, _U32, _U64, _I32, _D = "BOOL", "UINT8", "UINT32", "UINT64", "INT32", "DOUBLE"
_V3, _V6, _V6I = "VECTOR3D", "VECTOR6D", "VECTOR6INT32"


def _warming(uptime_s: float) -> list[float]:
    """The joints' temperatures (°C) after ``uptime_s`` of the controller."""
    cold = COLD_BY_C * math.exp(-uptime_s / WARM_TAU_S)
    return [t - cold for t in TEMPERATURES]


def _registers(side: str) -> dict[str, str]:
    """The general-purpose registers of one side: bits 64-127, ints and doubles 0-47."""
    out = {f"{side}_bit_register_{i}": _B for i in range(64, 128)}
    out |= {f"{side}_int_register_{i}": _I32 for i in range(48)}
    return out | {f"{side}_double_register_{i}": _D for i in range(48)}


OUTPUT_TYPES: dict[str, str] = {
    "timestamp": _D,
    "target_q": _V6,
    "target_qd": _V6,
    "target_qdd": _V6,
    "target_current": _V6,
    "target_moment": _V6,
    "actual_q": _V6,
    "actual_qd": _V6,
    "actual_current": _V6,
    "actual_current_window": _V6,
    "joint_control_output": _V6,
    "actual_TCP_pose": _V6,
    "actual_TCP_speed": _V6,
    "actual_TCP_force": _V6,
    "target_TCP_pose": _V6,
    "target_TCP_speed": _V6,
    "tcp_offset": _V6,
    "actual_digital_input_bits": _U64,
    "actual_configurable_digital_input_bits": _U64,
    "joint_temperatures": _V6,
    "actual_execution_time": _D,
    "robot_mode": _I32,
    "joint_mode": _V6I,
    "safety_mode": _I32,
    "safety_status": _I32,
    "actual_tool_accelerometer": _V3,
    "speed_scaling": _D,
    "target_speed_fraction": _D,
    "actual_momentum": _D,
    "actual_main_voltage": _D,
    "actual_robot_voltage": _D,
    "actual_robot_current": _D,
    "actual_joint_voltage": _V6,
    "actual_digital_output_bits": _U64,
    "actual_configurable_digital_output_bits": _U64,
    "runtime_state": _U32,
    "elbow_position": _V3,
    "elbow_velocity": _V3,
    "robot_status_bits": _U32,
    "safety_status_bits": _U32,
    "analog_io_types": _U32,
    "standard_analog_input0": _D,
    "standard_analog_input1": _D,
    "standard_analog_output0": _D,
    "standard_analog_output1": _D,
    "io_current": _D,
    "encoder0_raw": _I32,
    "encoder1_raw": _I32,
    "euromap67_input_bits": _U32,
    "euromap67_output_bits": _U32,
    "euromap67_24V_voltage": _D,
    "euromap67_24V_current": _D,
    "tool_mode": _U32,
    "tool_analog_input_types": _U32,
    "tool_analog_input0": _D,
    "tool_analog_input1": _D,
    "tool_output_voltage": _I32,
    "tool_output_current": _D,
    "tool_temperature": _D,
    "tool_output_mode": _U8,
    "tool_digital_output0_mode": _U8,
    "tool_digital_output1_mode": _U8,
    "tcp_force_scalar": _D,
    "joint_position_deviation_ratio": _D,
    "collision_detection_ratio": _D,
    "ft_raw_wrench": _V6,
    "payload": _D,
    "payload_cog": _V3,
    "payload_inertia": _V6,
    "script_control_line": _U32,
    "time_scale_source": _I32,
    "output_bit_registers0_to_31": _U32,
    "output_bit_registers32_to_63": _U32,
    "input_bit_registers0_to_31": _U32,
    "input_bit_registers32_to_63": _U32,
}
OUTPUT_TYPES |= _registers("output") | _registers("input")

#: Outputs of the guide that came with software after 5.11: NOT_FOUND, as on a 5.11.
LATER_OUTPUTS = frozenset(
    {
        "actual_current_as_torque",
        "actual_TCP_acceleration",
        "target_TCP_acceleration",
        "target_execution_time",
        "actual_robot_energy_consumed",
        "actual_robot_braking_energy_dissipated",
        "wrench_calc_from_currents",
        "target_gravity",
        "target_base_acceleration",
        "target_base_wrench",
        "control_step",
    }
)

INPUT_TYPES: dict[str, str] = {
    "speed_slider_mask": _U32,
    "speed_slider_fraction": _D,
    "standard_digital_output_mask": _U8,
    "standard_digital_output": _U8,
    "configurable_digital_output_mask": _U8,
    "configurable_digital_output": _U8,
    "tool_digital_output_mask": _U8,
    "tool_digital_output": _U8,
    "standard_analog_output_mask": _U8,
    "standard_analog_output_type": _U8,
    "standard_analog_output_0": _D,
    "standard_analog_output_1": _D,
    "input_bit_registers0_to_31": _U32,
    "input_bit_registers32_to_63": _U32,
    "external_force_torque": _V6,
}
INPUT_TYPES |= _registers("input")

_REG = re.compile(r"(input|output)_(int|double|bit)_register_(\d+)")

# Constant values of a UR10e holding still, unloaded (SI units: A, N·m, °C, V, m/s², N).
CURRENTS = [0.05, -3.1, -1.6, -0.32, 0.03, 0.0]
MOMENTS = [0.1, -58.0, -21.0, -1.9, 0.2, 0.0]
CONTROL_OUTPUT = [0.05, -3.05, -1.58, -0.31, 0.03, 0.0]
CURRENT_WINDOW = [0.4, 0.6, 0.6, 0.3, 0.3, 0.3]
TEMPERATURES = [31.6, 33.9, 33.1, 35.4, 34.7, 34.2]  # each joint's working temperature
#: how much colder the joints are when the controller starts (°C), and how fast they warm
COLD_BY_C, WARM_TAU_S = 8.0, 600.0
TCP_FORCE = [1.2, -0.8, 2.1, 0.05, -0.04, 0.01]
ACCELEROMETER = [0.02, -0.03, 9.79]
ELBOW = [-0.6127, -0.1807, 0.1807]
PAYLOAD_COG = [0.0, 0.0, 0.05]
JOINT_VOLTAGE = [47.6, 47.5, 47.6, 47.8, 47.7, 47.7]
TOOL_RUNNING = 253
JOINT_MODE_BY_ROBOT_MODE = {3: 239, 5: 255, 7: 253}  # power off, idle, running


class Fields:
    """Getters of the outputs and setters of the inputs, bound to one controller."""

    def __init__(self, ctl: Controller) -> None:
        self.ctl = ctl
        c = ctl
        zeros6 = [0.0] * 6
        scalar = math.sqrt(sum(f * f for f in TCP_FORCE[:3]))
        self.fixed: dict[str, Callable[[], Any]] = {
            "timestamp": lambda: c.cycle * CYCLE_S,
            "target_q": lambda: c.q_pub,
            "actual_q": lambda: c.q_pub,
            "target_qd": lambda: c.qd_pub,
            "actual_qd": lambda: c.qd_pub,
            "target_qdd": lambda: c.qdd_pub,
            "target_current": lambda: CURRENTS,
            "actual_current": lambda: CURRENTS,
            "target_moment": lambda: MOMENTS,
            "joint_control_output": lambda: CONTROL_OUTPUT,
            "actual_current_window": lambda: CURRENT_WINDOW,
            "actual_TCP_pose": lambda: c.tcp,
            "target_TCP_pose": lambda: c.tcp,
            "actual_TCP_speed": lambda: c.tcp_speed,
            "target_TCP_speed": lambda: c.tcp_speed,
            "actual_TCP_force": lambda: TCP_FORCE,
            "tcp_force_scalar": lambda: scalar,
            "tcp_offset": lambda: zeros6,
            "ft_raw_wrench": lambda: TCP_FORCE,
            "joint_temperatures": lambda: _warming(c.cycle * CYCLE_S),
            "actual_execution_time": lambda: 0.35,
            "robot_mode": lambda: c.robot_mode,
            "joint_mode": lambda: [JOINT_MODE_BY_ROBOT_MODE.get(c.robot_mode, 253)] * 6,
            "safety_mode": c.safety_mode,
            "safety_status": c.safety_mode,
            "actual_tool_accelerometer": lambda: ACCELEROMETER,
            "speed_scaling": lambda: 1.0,
            "target_speed_fraction": lambda: c.speed_fraction,
            "actual_main_voltage": lambda: 48.1,
            "actual_robot_voltage": lambda: 0.0 if c.robot_mode == 3 else 47.9,
            "actual_robot_current": lambda: 0.0 if c.robot_mode == 3 else 0.92,
            "actual_joint_voltage": lambda: [0.0] * 6 if c.robot_mode == 3 else JOINT_VOLTAGE,
            "actual_digital_output_bits": lambda: c.digital_outputs,
            "actual_configurable_digital_output_bits": lambda: (c.digital_outputs >> 8) & 0xFF,
            "runtime_state": lambda: c.runtime_state,
            "elbow_position": lambda: ELBOW,
            "robot_status_bits": c.robot_status_bits,
            "safety_status_bits": c.safety_bits,
            "standard_analog_output0": lambda: c.analog_outputs[0],
            "standard_analog_output1": lambda: c.analog_outputs[1],
            "io_current": lambda: 0.06,
            "tool_mode": lambda: TOOL_RUNNING,
            "tool_temperature": lambda: 32.4,
            "tool_digital_output0_mode": lambda: 1,
            "tool_digital_output1_mode": lambda: 1,
            "payload": lambda: c.payload,
            "payload_cog": lambda: PAYLOAD_COG,
            "output_bit_registers0_to_31": lambda: c.out_bits & 0xFFFFFFFF,
            "output_bit_registers32_to_63": lambda: (c.out_bits >> 32) & 0xFFFFFFFF,
            "input_bit_registers0_to_31": lambda: c.in_bits & 0xFFFFFFFF,
            "input_bit_registers32_to_63": lambda: (c.in_bits >> 32) & 0xFFFFFFFF,
        }

    def getter(self, name: str) -> Callable[[], Any] | None:
        """The value of output ``name`` each cycle; None for NOT_FOUND."""
        typ = OUTPUT_TYPES.get(name)
        if typ is None:
            return None
        if name in self.fixed:
            return self.fixed[name]
        c = self.ctl
        m = _REG.fullmatch(name)
        if m is not None:
            io, kind, idx = m.group(1), m.group(2), int(m.group(3))
            if kind == "int":
                ints = c.out_int if io == "output" else c.in_int
                return lambda: ints[idx]
            if kind == "double":
                doubles = c.out_double if io == "output" else c.in_double
                return lambda: doubles[idx]
            if io == "output":
                return lambda: bool((c.out_bits >> idx) & 1)
            return lambda: bool((c.in_bits >> idx) & 1)
        zero: Any = {_V6: [0.0] * 6, _V3: [0.0] * 3, _V6I: [0] * 6, _D: 0.0, _B: False}.get(typ, 0)
        return lambda: zero

    def set_inputs(self, values: dict[str, Any]) -> None:
        """Apply one input data package (masks and values together, as the guide says)."""
        c = self.ctl
        for name, value in values.items():
            m = _REG.fullmatch(name)
            if m is not None:
                kind, idx = m.group(2), int(m.group(3))
                if kind == "int":
                    c.in_int[idx] = int(value)
                elif kind == "double":
                    c.in_double[idx] = float(value)
                elif value:
                    c.in_bits |= 1 << idx
                else:
                    c.in_bits &= ~(1 << idx)
            elif name == "input_bit_registers0_to_31":
                c.in_bits = (c.in_bits & ~0xFFFFFFFF) | int(value)
            elif name == "input_bit_registers32_to_63":
                c.in_bits = (c.in_bits & ~(0xFFFFFFFF << 32)) | (int(value) << 32)
            else:
                c.inputs_misc[name] = value
        misc = c.inputs_misc
        if int(misc.get("speed_slider_mask", 0)) & 1 and "speed_slider_fraction" in values:
            c.speed_fraction = min(max(float(misc["speed_slider_fraction"]), 0.0), 1.0)
        for shift, prefix in ((0, "standard"), (8, "configurable"), (16, "tool")):
            if f"{prefix}_digital_output" in values or f"{prefix}_digital_output_mask" in values:
                mask = (int(misc.get(f"{prefix}_digital_output_mask", 0)) & 0xFF) << shift
                bits = (int(misc.get(f"{prefix}_digital_output", 0)) & 0xFF) << shift
                c.digital_outputs = (c.digital_outputs & ~mask) | (bits & mask)
        analog_mask = int(misc.get("standard_analog_output_mask", 0))
        for k in (0, 1):
            if analog_mask & (1 << k) and f"standard_analog_output_{k}" in values:
                c.analog_outputs[k] = float(values[f"standard_analog_output_{k}"])
