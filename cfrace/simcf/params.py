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
BRUSHLESS_LOW_VOLTAGE = 3.35   #: V, the Brushless's pm.lowVoltage
#: The firmware release the simulated Crazyflie reports (platformservice.c: V_STAG) and its commit, whose
#: first 12 hex digits are the read-only firmware.revision0 (8) and revision1 (4) (version.vtpl)
FIRMWARE_RELEASE = "2026.08"
FIRMWARE_REVISION = "54f31e243a0b28b67efef5ba20dbb6d9890a5478"


def device_type_name(arming_required: bool) -> str:
    """The platform's name as the firmware reports it (platform_cf2.c, platform_cf21bl.c: deviceTypeName):
    the platforms that need arming are the 2.1 Brushless."""
    return "Crazyflie 2.1 Brushless" if arming_required else "Crazyflie 2.1"


PARAM_TYPES = {"int8_t": (0x00, "<b"), "int16_t": (0x01, "<h"), "int32_t": (0x02, "<i"),
               "float": (0x06, "<f"), "uint8_t": (0x08, "<B"), "uint16_t": (0x09, "<H"),
               "uint32_t": (0x0A, "<I")}

def _group(group: str, ctype: str, entries, readonly: bool = False, doc: str = "") -> tuple[ParamSpec, ...]:
    """ParamSpecs of one group: entries are (name, default) pairs."""
    return tuple(ParamSpec(f"{group}.{name}", ctype, default, readonly, doc) for name, default in entries)


def _gains(axes, suffixes, values) -> list[tuple[str, float]]:
    """[(axis + suffix, value)] for each axis, e.g. roll_kp, roll_ki, roll_kd."""
    return [(f"{a}{s}", v) for a, vals in zip(axes, values) for s, v in zip(suffixes, vals)]


#: Defaults of the firmware's PID controller (controller_pid.c, attitude_pid_controller.c,
#: position_controller_pid.c; platform defaults of the Crazyflie 2.x and 2.1 Brushless, which agree
#: on these): attitude deg -> deg/s, velocity m/s -> deg (roll/pitch) or thrust/1000 (z), position m -> m/s.
ATTITUDE_GAINS = ((6.0, 3.0, 0.0), (6.0, 3.0, 0.0), (6.0, 1.0, 0.35))          #: roll, pitch, yaw (kp, ki, kd)
ATTITUDE_I_LIMIT = (20.0, 20.0, 360.0)                                        #: deg s
VELOCITY_GAINS = ((25.0, 1.0, 0.0), (25.0, 1.0, 0.0), (25.0, 15.0, 0.0))       #: vx, vy, vz
POSITION_GAINS = ((2.0, 0.0, 0.0), (2.0, 0.0, 0.0), (2.0, 0.5, 0.0))          #: x, y, z
#: ctrlMel.* of the Mellinger controller (controller_mellinger.c, g_self): N/m, N s/m, N/(m s) on
#: position; moment gains on attitude (kR), rates (kw) and their integrals. mass (kg) and massThrust
#: (counts per N) are set from the drone's profile (the firmware's: CF_MASS and 132000).
MELLINGER_GAINS = (("kp_xy", 0.4), ("kd_xy", 0.2), ("ki_xy", 0.05), ("i_range_xy", 2.0),
                   ("kp_z", 1.25), ("kd_z", 0.4), ("ki_z", 0.05), ("i_range_z", 0.4),
                   ("mass", 0.029), ("massThrust", 132000.0),
                   ("kR_xy", 70000.0), ("kR_z", 60000.0), ("kw_xy", 20000.0), ("kw_z", 12000.0),
                   ("ki_m_xy", 0.0), ("ki_m_z", 500.0), ("kd_omega_rp", 200.0),
                   ("i_range_m_xy", 1.0), ("i_range_m_z", 1500.0))
PID_I_LIMIT = 5000.0                                                          #: the firmware's default
THRUST_BASE_FIRMWARE = 36000   #: counts, posCtlPid.thrustBase of the Crazyflie 2.x (our default: the profile's hover)

#: The emulated parameters, in TOC order. Defaults marked "profile" are set per drone from its profile
#: (see default_params); "deck" ones from the simulated drone's positioning decks.
PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("flightmode.stabModeRoll", "uint8_t", 1, doc="0 rate, 1 angle (firmware default 1)"),
    ParamSpec("flightmode.stabModePitch", "uint8_t", 1, doc="0 rate, 1 angle (firmware default 1)"),
    ParamSpec("flightmode.stabModeYaw", "uint8_t", 0, doc="0 rate (default), 1 angle"),
    ParamSpec("stabilizer.estimator", "uint8_t", 2,
              doc="0 auto, 1 complementary, 2 Kalman: reported; the simulated drone always runs its Kalman filter"),
    ParamSpec("stabilizer.controller", "uint8_t", 1,
              doc="0 auto, 1 PID, 2 Mellinger (simcf/mellinger.py); others: a console warning, PID runs"),
    ParamSpec("stabilizer.stop", "uint8_t", 0, doc="nonzero -> emergency stop"),
    ParamSpec("led.bitmask", "uint8_t", 0, doc="the LEDs' override bits (led.c): accepted, no LEDs are simulated"),
    ParamSpec("commander.enHighLevel", "uint8_t", 0, doc="accepted, no effect (as in the firmware)"),
    ParamSpec("supervisor.armingReq", "uint8_t", 1, readonly=True,
              doc="simulator info: 1 if motors need an arming request"),
    ParamSpec("simcf.bodyIndex", "uint8_t", 0, readonly=True, doc="simulator info: drone index"),
    ParamSpec("firmware.revision0", "uint32_t", int(FIRMWARE_REVISION[:8], 16), readonly=True,
              doc="bytes 0-7 of the release's commit (version.vtpl)"),
    ParamSpec("firmware.revision1", "uint16_t", int(FIRMWARE_REVISION[8:12], 16), readonly=True,
              doc="bytes 8-11 of the release's commit"),
    ParamSpec("firmware.modified", "uint8_t", 0, readonly=True, doc="nonzero if the firmware has local changes"),
    # the firmware's motor test override (motors.c): enable 1 = each motor its own value, 2 = m1 to
    # all motors, 3 = m1 to all with battery compensation; 0 = off. Used by the thrust stand
    # (cfrace calibrate, simulated by rehearsal/thrust_stand.py; without a stand these have no effect).
    ParamSpec("motorPowerSet.enable", "uint8_t", 0, doc="motor override: 0 off, 1 per motor, 2 m1 to all, 3 + battery comp."),
    ParamSpec("motorPowerSet.m1", "uint16_t", 0, doc="motor 1 command, counts 0-65535"),
    ParamSpec("motorPowerSet.m2", "uint16_t", 0, doc="motor 2 command, counts"),
    ParamSpec("motorPowerSet.m3", "uint16_t", 0, doc="motor 3 command, counts"),
    ParamSpec("motorPowerSet.m4", "uint16_t", 0, doc="motor 4 command, counts"),
    *_group("pid_attitude", "float", _gains(("roll", "pitch", "yaw"), ("_kp", "_ki", "_kd"), ATTITUDE_GAINS),
            doc="attitude PID: error deg -> rate deg/s"),
    *_group("pid_rate", "float", _gains(("roll", "pitch", "yaw"), ("_kp", "_ki", "_kd"), ((0, 0, 0),) * 3),
            readonly=True, doc="profile: the simulator's body-rate PID (read-only here)"),
    *_group("velCtlPid", "float", _gains(("vx", "vy", "vz"), ("Kp", "Ki", "Kd"), VELOCITY_GAINS),
            doc="velocity PID: m/s -> roll/pitch deg; z: -> thrust / 1000 counts"),
    *_group("posCtlPid", "float", _gains("xyz", ("Kp", "Ki", "Kd"), POSITION_GAINS), doc="position PID: m -> m/s"),
    ParamSpec("posCtlPid.thrustBase", "uint16_t", THRUST_BASE_FIRMWARE, doc="profile: counts at hover"),
    ParamSpec("posCtlPid.thrustMin", "uint16_t", 20000, doc="counts, least thrust of the velocity controller"),
    *_group("posCtlPid", "float", (("rLimit", 20.0), ("pLimit", 20.0), ("xVelMax", 1.0), ("yVelMax", 1.0),
                                   ("zVelMax", 1.0)), doc="deg (limits), m/s (velocities)"),
    *_group("ctrlMel", "float", MELLINGER_GAINS, doc="Mellinger controller (stabilizer.controller 2)"),
    ParamSpec("kalman.resetEstimation", "uint8_t", 0, doc="nonzero: reset the estimator (then set back to 0)"),
    *_group("kalman", "float", (("pNAcc_xy", 0.5), ("pNAcc_z", 1.0), ("pNVel", 0.0), ("pNPos", 0.0),
                                ("initialX", 0.0), ("initialY", 0.0), ("initialZ", 0.0), ("initialYaw", 0.0)),
            doc="process noise (m/s^2, m/s, m) and the state after a reset (m, rad)"),
    *_group("locSrv", "float", (("extPosStdDev", 0.01), ("extQuatStdDev", 4.5e-3)),
            doc="std dev of external position (m) and attitude (rad) measurements"),
    *_group("locSrv", "uint8_t", (("enRangeStreamFP32", 0), ("enLhAngleStream", 0), ("enLhMtchStm", 0),
                                  ("maxTimeLhMtchStm", 25), ("minBsLhMtchStm", 2)),
            doc="Loco and Lighthouse streams to the client (crtp_localization_service.c): accepted, no effect"),
    *_group("hlCommander", "float", (("vtoff", 0.5), ("vland", 0.2)), doc="m/s, default take-off / landing speed"),
    ParamSpec("hlCommander.groupmask", "uint8_t", 0,
              doc="the groups (bits) of this drone for the high-level commander's group masks; 0: none"),
    ParamSpec("pm.lowVoltage", "float", 3.2, doc="V, below for 5 s: pm.state low power (3.35 on the Brushless)"),
    ParamSpec("pm.criticalLowVoltage", "float", 3.0, doc="V, critically low battery"),
    ParamSpec("powerDist.idleThrust", "uint32_t", 0,
              doc="counts, least command of each armed motor (7000 on the Crazyflie 2.1 Brushless)"),
    ParamSpec("supervisor.tmblChckEn", "uint8_t", 1, doc="nonzero: a tumble crashes a flying drone (supervisor.c)"),
    ParamSpec("supervisor.crashDetectGs", "float", 0.0,
              doc="g, a crash: | |acc| - 1 g | above this counts as tumbled; 0: off (supervisor.c)"),
    ParamSpec("supervisor.prefltTimeout", "uint16_t", 30000, doc="ms armed without flying before disarming"),
    ParamSpec("supervisor.landedTimeout", "uint16_t", 3000, doc="ms after landing before disarming"),
    *_group("deck", "uint8_t", (("bcLighthouse4", 0), ("bcFlow2", 0), ("bcLedRing", 0)), readonly=True,
            doc="deck: 1 if the simulated drone carries this deck"),
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


def default_params(index: int, arming_required: bool, overrides: dict | None = None) -> dict:
    """Every parameter's value at boot; ``overrides`` {name: value} replace the table's defaults
    (the drone's profile and decks: see SimFleet.param_defaults)."""
    values = {p.name: coerce_param(p, p.default) for p in PARAMS}
    values["supervisor.armingReq"] = int(arming_required)
    # The platforms that need arming are the Brushless ones, whose firmware boots with
    # CONFIG_MOTORS_DEFAULT_IDLE_THRUST 7000. The simulator boots with 0 (docs/simcf.md, "Idle
    # thrust"): the floor cannot be undone from the ground, and the shipped policies, trained
    # without it, fly other lines with it. A fleet's params (SimFleet, dry-run --idle-thrust) set it.
    values["powerDist.idleThrust"] = 0
    if arming_required:
        values["pm.lowVoltage"] = coerce_param(PARAM_BY_NAME["pm.lowVoltage"], BRUSHLESS_LOW_VOLTAGE)
    values["simcf.bodyIndex"] = index
    for name, value in (overrides or {}).items():
        values[name] = coerce_param(PARAM_BY_NAME[name], value)
    return values
