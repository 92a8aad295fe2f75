"""Drone parameter profiles (calibration/*.yaml): physics, rate PID, action map, thrust curve.

Every parameter must carry a source in the file's ``sources:`` mapping (strict loader).
SI units throughout; the only non-SI numbers are CRTP thrust counts in the thrust curve and the
max rates, given in deg/s as the paper and the firmware state them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cfrace.paths import CALIBRATION_DIR
from cfrace.yamlcfg import Reader, open_named

GRAVITY = 9.81  #: m/s^2

#: The profile that training and evaluation use unless told otherwise (see docs/drones.md).
DEFAULT_PROFILE = "cf2x_paper"

_PARAM_KEYS = ("mass", "inertia", "arm_length", "rotor_dirs", "k_eta", "k_m", "tau_m", "motor_speed",
               "max_thrust_weights", "max_rates_deg", "pid_roll_pitch", "pid_yaw", "k_aero",
               "collision_box", "thrust_curve")


@dataclass(frozen=True)
class PID:
    kp: float       #: 1/s, proportional gain on the rate error (output: angular acceleration)
    ki: float       #: 1/s^2, integral gain
    kd: float       #: -, derivative gain on the measured rate
    i_limit: float  #: rad, clamp of the integrated rate error


@dataclass(frozen=True)
class ThrustCurve:
    counts: tuple[float, ...]   #: CRTP thrust command, uint16 counts, increasing
    newtons: tuple[float, ...]  #: collective thrust, N, increasing

    def to_newtons(self, counts):
        return np.interp(counts, self.counts, self.newtons)

    def to_counts(self, newtons):
        """Collective thrust (N) -> uint16 counts, clamped to the curve's range."""
        return np.interp(newtons, self.newtons, self.counts)


@dataclass(frozen=True)
class DroneProfile:
    name: str
    description: str
    mass: float                             #: kg
    inertia: tuple[float, float, float]     #: kg m^2 (diagonal)
    arm_length: float                       #: m
    rotor_dirs: tuple[float, ...]           #: spin directions of rotors 1..4
    k_eta: float                            #: N/(rad/s)^2
    k_m: float                              #: N m/(rad/s)^2
    tau_m: float                            #: s
    motor_speed: tuple[float, float]        #: rad/s (min, max)
    max_thrust_weights: float               #: action map T (units of weight)
    max_rates_deg: tuple[float, float, float]  #: deg/s
    pid_roll_pitch: PID
    pid_yaw: PID
    k_aero: tuple[float, float, float]      #: N s/m per rad/s of summed rotor speed
    collision_box: tuple[float, float, float]  #: m
    thrust_curve: ThrustCurve
    sources: dict
    source: str = ""

    @property
    def weight(self) -> float:
        return self.mass * GRAVITY

    @property
    def max_rates(self) -> tuple[float, float, float]:
        """rad/s"""
        return tuple(math.radians(v) for v in self.max_rates_deg)

    @property
    def max_collective_thrust(self) -> float:
        """N, all motors at max speed."""
        return 4.0 * self.k_eta * self.motor_speed[1] ** 2

    @property
    def rotor_xy(self) -> np.ndarray:
        """(4, 2) rotor positions in the body frame: r1 (+,+), r2 (+,-), r3 (-,-), r4 (-,+)."""
        a = self.arm_length / math.sqrt(2.0)
        return np.array([[a, a], [a, -a], [-a, -a], [-a, a]])

    def allocation(self) -> np.ndarray:
        """(4, 4) thrust-to-wrench map: [f_z, tau_x, tau_y, tau_z] = A @ rotor forces."""
        xy = self.rotor_xy
        return np.stack([np.ones(4), xy[:, 1], -xy[:, 0], (self.k_m / self.k_eta) * np.asarray(self.rotor_dirs)])

    @property
    def collision_radius(self) -> float:
        """m, radius of the sphere used for contacts (half the larger box side)."""
        return max(self.collision_box[0], self.collision_box[1]) / 2.0


def _pid(r: Reader, key: str) -> PID:
    p = r.mapping(key)
    pid = PID(p.number("kp", min=0.0), p.number("ki", min=0.0), p.number("kd", min=0.0), p.number("i_limit", min=0.0))
    p.done()
    return pid


def load_profile(name_or_path: str | Path = DEFAULT_PROFILE) -> DroneProfile:
    """Load a drone profile by name (calibration/NAME.yaml) or path; strict."""
    r = open_named(name_or_path, CALIBRATION_DIR, "drone profile")
    name = r.file_name(CALIBRATION_DIR)
    description = r.string("description", "")
    mass = r.number("mass", positive=True)
    inertia = r.vector("inertia", 3, positive=True)
    arm = r.number("arm_length", positive=True)
    dirs = r.vector("rotor_dirs", 4)
    if sorted(dirs) != [-1.0, -1.0, 1.0, 1.0]:
        raise r.fail("rotor_dirs", "must hold two +1 and two -1")
    k_eta = r.number("k_eta", positive=True)
    k_m = r.number("k_m", positive=True)
    tau_m = r.number("tau_m", positive=True)
    speed = r.vector("motor_speed", 2, min=0.0)
    if speed[0] >= speed[1]:
        raise r.fail("motor_speed", "must be [min, max] with min < max")
    t_max = r.number("max_thrust_weights", positive=True)
    rates = r.vector("max_rates_deg", 3, positive=True)
    pid_rp, pid_yaw = _pid(r, "pid_roll_pitch"), _pid(r, "pid_yaw")
    k_aero = r.vector("k_aero", 3, min=0.0)
    box = r.vector("collision_box", 3, positive=True)
    tc = r.mapping("thrust_curve")
    counts = tc.vector("counts", None, min=0.0, max=65535.0)
    newtons = tc.vector("newtons", len(counts), min=0.0)
    tc.done()
    if len(counts) < 2 or any(b <= a for a, b in zip(counts, counts[1:])) or any(
            b <= a for a, b in zip(newtons, newtons[1:])):
        raise r.fail("thrust_curve", "needs >= 2 points, counts and newtons strictly increasing")
    sources = r.raw("sources")
    if not isinstance(sources, dict):
        raise r.fail("sources", "expected a mapping from parameter to its source")
    for key in _PARAM_KEYS:
        if not isinstance(sources.get(key), str) or not sources[key].strip():
            raise r.fail(f"sources.{key}", "missing: every parameter must name its source")
    extra = sorted(set(sources) - set(_PARAM_KEYS))
    if extra:
        raise r.fail(f"sources.{extra[0]}", "unknown key")
    r.done()
    return DroneProfile(name, description, mass, inertia, arm, dirs, k_eta, k_m, tau_m, speed, t_max, rates,
                        pid_rp, pid_yaw, k_aero, box, ThrustCurve(counts, newtons), dict(sources), r.path)


def list_profiles() -> list[Path]:
    return sorted(CALIBRATION_DIR.glob("*.yaml"))
