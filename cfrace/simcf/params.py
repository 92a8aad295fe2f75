"""Parameters of the simulated Crazyflie: the TOC the firmware emulation exposes over CRTP."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ParamSpec:
    name: str        #: "group.name"
    ctype: str       #: one of PARAM_TYPES
    default: float
    readonly: bool = False
    doc: str = ""


#: CRTP parameter type codes (firmware param.h; cflib ParamTocElement.types): ctype -> (code, struct)
PARAM_TYPES = {"int8_t": (0x00, "<b"), "int16_t": (0x01, "<h"), "int32_t": (0x02, "<i"),
               "float": (0x06, "<f"), "uint8_t": (0x08, "<B"), "uint16_t": (0x09, "<H"),
               "uint32_t": (0x0A, "<I")}

#: The emulated parameters, in TOC order.
PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("flightmode.stabModeRoll", "uint8_t", 1, doc="0 rate, 1 angle (firmware default 1)"),
    ParamSpec("flightmode.stabModePitch", "uint8_t", 1, doc="0 rate, 1 angle (firmware default 1)"),
    ParamSpec("flightmode.stabModeYaw", "uint8_t", 0, doc="0 rate (default), 1 angle"),
    ParamSpec("stabilizer.estimator", "uint8_t", 2, doc="reported only (2 = Kalman); ground truth is used"),
    ParamSpec("stabilizer.controller", "uint8_t", 1, doc="reported only (1 = PID)"),
    ParamSpec("stabilizer.stop", "uint8_t", 0, doc="nonzero -> emergency stop"),
    ParamSpec("commander.enHighLevel", "uint8_t", 0, doc="accepted, no effect (as in the firmware)"),
    ParamSpec("supervisor.armingReq", "uint8_t", 1, readonly=True,
              doc="simulator info: 1 if motors need an arming request"),
    ParamSpec("simcf.bodyIndex", "uint8_t", 0, readonly=True, doc="simulator info: drone index"),
    # the firmware's motor test override (motors.c): enable 1 = each motor its own value, 2 = m1 to
    # all motors, 3 = m1 to all with battery compensation; 0 = off. Used by the thrust stand
    # (cfrace calibrate, simulated by simcf/stand.py; without a stand these have no effect).
    ParamSpec("motorPowerSet.enable", "uint8_t", 0, doc="motor override: 0 off, 1 per motor, 2 m1 to all, 3 + battery comp."),
    ParamSpec("motorPowerSet.m1", "uint16_t", 0, doc="motor 1 command, counts 0-65535"),
    ParamSpec("motorPowerSet.m2", "uint16_t", 0, doc="motor 2 command, counts"),
    ParamSpec("motorPowerSet.m3", "uint16_t", 0, doc="motor 3 command, counts"),
    ParamSpec("motorPowerSet.m4", "uint16_t", 0, doc="motor 4 command, counts"),
)
PARAM_BY_NAME = {p.name: p for p in PARAMS}


def _int_range(ctype: str) -> tuple[int, int]:
    bits = int("".join(c for c in ctype if c.isdigit()))
    return (0, 2 ** bits - 1) if ctype.startswith("u") else (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1)


def coerce_param(spec: ParamSpec, value) -> float | int:
    """A value as the firmware would store it (ints wrap like the C types, floats as float32)."""
    if spec.ctype == "float":
        return float(np.float32(value))
    lo, hi = _int_range(spec.ctype)
    v = int(value)
    span = hi - lo + 1
    return (v - lo) % span + lo


def default_params(index: int, arming_required: bool) -> dict:
    values = {p.name: coerce_param(p, p.default) for p in PARAMS}
    values["supervisor.armingReq"] = int(arming_required)
    values["simcf.bodyIndex"] = index
    return values
