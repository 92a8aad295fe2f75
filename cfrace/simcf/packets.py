"""What the simulated Crazyflie's CRTP packets carry: the log variable table and the decoders of
the generic commander's setpoints and of the high-level commander's commands (layouts: the
firmware's crtp_commander_generic.c and crtp_commander_high_level.c, as cflib packs them)."""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

import numpy as np

from cfrace.simcf.controller import ABS, VELOCITY, Setpoint

#: log variable type codes (firmware log.h; cflib LogTocElement.types): code -> (struct, size)
LOG_TYPES = {0x01: ("<B", 1), 0x02: ("<H", 2), 0x03: ("<I", 4), 0x04: ("<b", 1), 0x05: ("<h", 2),
             0x06: ("<i", 4), 0x07: ("<f", 4), 0x08: ("<e", 2)}
_FLOAT, _U8, _U16, _I8, _I16 = 0x07, 0x01, 0x02, 0x04, 0x05

#: The emulated log TOC, in order: (name, stored type). Values come from SimFleet.log_values.
LOG_VARS: tuple[tuple[str, int], ...] = tuple(
    [(f"stateEstimate.{n}", _FLOAT) for n in ("x", "y", "z", "vx", "vy", "vz", "roll", "pitch", "yaw",
                                                 "qw", "qx", "qy", "qz")]
    + [(f"gyro.{n}", _FLOAT) for n in "xyz"]
    + [("stabilizer.thrust", _FLOAT), ("pm.vbat", _FLOAT), ("pm.state", _I8), ("supervisor.info", _U16),
       ("sys.canfly", _U8), ("sys.isFlying", _U8), ("sys.isTumbled", _U8)]
    # motor speeds (group rpm, uint16 revolutions per minute, as the firmware logs them where the drone
    # measures them, e.g. the 2.1 Brushless's ESC telemetry) and the motor commands (group motor,
    # counts): non-zero only on the simulated thrust stand (rehearsal/thrust_stand.py)
    + [(f"rpm.m{k}", _U16) for k in range(1, 5)] + [(f"motor.m{k}", _U16) for k in range(1, 5)]
    + [(f"motor.m{k}_rpm", _U16) for k in range(1, 5)]
    # estimator.c's compressed state: mm, mm/s, mm/s^2 as int16; ctrltarget.thrust (counts)
    + [(f"stateEstimateZ.{n}", _I16) for n in ("x", "y", "z", "vx", "vy", "vz", "ax", "ay", "az")]
    + [("ctrltarget.thrust", _FLOAT)]
    # the standard groups of the firmware's stabilizer, estimator, controller and power management
    + [(f"stateEstimate.{n}", _FLOAT) for n in ("ax", "ay", "az")]
    + [(f"stabilizer.{n}", _FLOAT) for n in ("roll", "pitch", "yaw")]
    + [(f"acc.{n}", _FLOAT) for n in "xyz"]
    + [(f"kalman.{n}", _FLOAT) for n in ("stateX", "stateY", "stateZ", "statePX", "statePY", "statePZ",
                                         "varX", "varY", "varZ", "varPX", "varPY", "varPZ", "q0", "q1", "q2", "q3")]
    + [(f"ctrltarget.{n}", _FLOAT) for n in ("x", "y", "z", "vx", "vy", "vz", "roll", "pitch", "yaw")]
    + [(f"controller.{n}", _FLOAT) for n in ("cmd_thrust", "roll", "pitch", "yaw", "rollRate", "pitchRate", "yawRate")]
    + [(f"posCtl.{n}", _FLOAT) for n in ("targetVX", "targetVY", "targetVZ", "targetX", "targetY", "targetZ")]
    + [("pm.vbatMV", _U16), ("pm.batteryLevel", _U8), ("range.zrange", _U16)]
    # crtp_localization_service.c: the last external position and pose, the tick of the last one
    + [(f"ext_pos.{n}", _FLOAT) for n in "XYZ"]
    + [(f"locSrv.{n}", _FLOAT) for n in ("x", "y", "z", "qx", "qy", "qz", "qw")] + [("locSrvZ.tick", _U16)])


EXT_POSE = 8   #: localization generic channel: external pose x y z qx qy qz qw
EXT_POSE_PACKED = 9   #: localization generic channel: up to 2 items <BhhhI (id, x y z mm, quat compressed)
EXT_POSITION_PACKED = 2   #: localization channel: up to 4 items <Bhhh (id, x y z mm)
_SMALL_MAX = 1.0 / math.sqrt(2.0)   #: the largest value a quaternion's three smaller components can have


def quat_decompress(comp: int) -> np.ndarray:
    """A quaternion compressed into 32 bits as the firmware decompresses it (quatcompress.h,
    quatdecompress): bits 31-30 the index of the largest component (order x y z w), then for the
    other three, highest index first in the low bits, a sign bit and a 9-bit magnitude scaled to
    1/sqrt(2); the largest is non-negative and restores the unit norm. -> wxyz."""
    mask = (1 << 9) - 1
    largest = comp >> 30
    q = [0.0] * 4
    squares = 0.0
    for k in (3, 2, 1, 0):
        if k == largest:
            continue
        mag, neg = comp & mask, (comp >> 9) & 1
        comp >>= 10
        q[k] = (-1.0 if neg else 1.0) * _SMALL_MAX * mag / mask
        squares += q[k] * q[k]
    q[largest] = math.sqrt(max(0.0, 1.0 - squares))
    return np.array([q[3], q[0], q[1], q[2]])

#: generic commander setpoint types (crtp_commander_generic.c): type -> name; the legacy ones (1, 2, 5)
#: carry a negated yaw rate (cflib sends -yawrate for firmware with protocol version <= 8)
GENERIC_TYPES = {1: "velocity_world_legacy", 2: "zdistance_legacy", 5: "hover_legacy", 7: "position",
                 8: "velocity_world", 9: "zdistance", 10: "hover", 11: "manual"}


def decode_generic(kind: int, data: bytes) -> Setpoint | None:
    """A generic-commander setpoint (payload after the type byte) -> Setpoint; None if the type is not
    emulated (cppm 3, alt-hold 4, full state 6). Raises struct.error on a short packet."""
    name = GENERIC_TYPES.get(kind)
    if name is None:
        return None
    sp = Setpoint(source=name)
    legacy_yaw = -1.0 if name.endswith("_legacy") else 1.0
    if name == "manual":
        roll, pitch, yawrate, thrust, rate = struct.unpack_from("<fffHB", data, 0)
        mode = VELOCITY if rate else ABS
        sp.mode_roll = sp.mode_pitch = mode
        target = sp.rates if rate else sp.attitude
        target[0], target[1] = math.radians(roll), -math.radians(pitch)
        sp.mode_yaw, sp.rates[2], sp.thrust = VELOCITY, math.radians(yawrate), float(thrust)
        return sp
    a, b, c, d = struct.unpack_from("<ffff", data, 0)
    if name == "position":
        sp.mode_x = sp.mode_y = sp.mode_z = sp.mode_yaw = ABS
        sp.position[:] = (a, b, c)
        sp.attitude[2] = math.radians(d)
        return sp
    sp.mode_yaw = VELOCITY
    if name.startswith("velocity_world"):
        sp.mode_x = sp.mode_y = sp.mode_z = VELOCITY
        sp.velocity[:] = (a, b, c)
        sp.rates[2] = legacy_yaw * math.radians(d)
    elif name.startswith("zdistance"):
        sp.mode_roll = sp.mode_pitch = sp.mode_z = ABS
        sp.attitude[0], sp.attitude[1] = math.radians(a), -math.radians(b)
        sp.rates[2], sp.position[2] = legacy_yaw * math.radians(c), d
    else:                                                   # hover: body-frame vx, vy, height
        sp.mode_x = sp.mode_y = VELOCITY
        sp.mode_z = ABS
        sp.velocity[:2], sp.velocity_body = (a, b), True
        sp.rates[2], sp.position[2] = legacy_yaw * math.radians(c), d
    return sp


def decode_high_level(payload: bytes) -> tuple[str, int, dict] | None:
    """A high-level commander packet -> (command, group mask, arguments for SimFleet.high_level);
    None if not emulated. Layouts: crtp_commander_high_level.c. Raises struct.error when short."""
    cmd = payload[0]
    if cmd == 0:                                            # set group mask
        return "set_group_mask", payload[1] if len(payload) > 1 else 0, {}
    if cmd == 3:                                            # stop
        return "stop", struct.unpack_from("<B", payload, 1)[0], {}
    if cmd in (1, 2):                                       # takeoff / land (v1): mask, height, duration
        mask, height, duration = struct.unpack_from("<Bff", payload, 1)
        return ("takeoff" if cmd == 1 else "land"), mask, {"height": height, "yaw": 0.0, "duration": duration}
    if cmd in (7, 8):                                       # takeoff / land (v2): + yaw, use current yaw
        mask, height, yaw, current, duration = struct.unpack_from("<Bff?f", payload, 1)
        return ("takeoff" if cmd == 7 else "land"), mask, {"height": height, "yaw": None if current else yaw,
                                                            "duration": duration}
    if cmd in (4, 12):                                      # go to (v1 / v2 with linear)
        if cmd == 4:
            mask, relative, x, y, z, yaw, duration = struct.unpack_from("<BBfffff", payload, 1)
            linear = 0
        else:
            mask, relative, linear, x, y, z, yaw, duration = struct.unpack_from("<BBBfffff", payload, 1)
        return "go_to", mask, {"x": x, "y": y, "z": z, "yaw": yaw, "duration": duration,
                               "relative": bool(relative), "linear": bool(linear)}
    if cmd in (5, 13):                                      # start trajectory (v1 / v2 with relative yaw)
        if cmd == 5:
            mask, relative, reversed_, ident, timescale = struct.unpack_from("<BBBBf", payload, 1)
            relative_yaw = 0
        else:
            mask, relative, relative_yaw, reversed_, ident, timescale = struct.unpack_from("<BBBBBf", payload, 1)
        return "start_trajectory", mask, {"trajectory_id": ident, "timescale": timescale,
                                          "relative_position": bool(relative), "relative_yaw": bool(relative_yaw),
                                          "reversed": bool(reversed_)}
    if cmd == 6:                                            # define trajectory: no group mask
        ident, location, kind, offset, n_pieces = struct.unpack_from("<BBBIB", payload, 1)
        return "define_trajectory", 0, {"trajectory_id": ident, "location": location, "kind": kind,
                                        "offset": offset, "n_pieces": n_pieces}
    if cmd == 11:                                           # spiral
        mask, sideways, clockwise, angle, r0, rf, ascent, duration = struct.unpack_from("<BBBfffff", payload, 1)
        return "spiral", mask, {"sideways": bool(sideways), "clockwise": bool(clockwise), "angle": angle, "r0": r0,
                                "rf": rf, "ascent": ascent, "duration": duration}
    return None


@dataclass
class LogBlock:
    ops: list = field(default_factory=list)   #: (variable index, fetch type code)
    period: float = 0.1                       #: s
    started: bool = False
    next_due: float = 0.0                     #: simulated time s

    def length(self) -> int:
        return sum(LOG_TYPES[t][1] for _, t in self.ops)


def pack_value(code: int, value) -> bytes:
    fmt, size = LOG_TYPES[code]
    if fmt in ("<f", "<e"):
        return struct.pack(fmt, float(value))
    lo, hi = (0, 2 ** (8 * size) - 1) if fmt[1].isupper() else (-(2 ** (8 * size - 1)), 2 ** (8 * size - 1) - 1)
    return struct.pack(fmt, max(lo, min(hi, int(round(float(value))))))
