"""The lab's loop between a drone and its policy, one model for training and for the dry-run.

A real room puts a motion-capture system, a host and a radio between a drone and the policy that
flies it: the pose the policy sees is 10-25 ms old, a little noisy, now and then missing, and the
setpoint that answers it may land one radio tick late; the drone itself is never exactly the one
the policy trained on. This module holds the one definition of that loop:

- ``LoopRanges``: what training draws per episode (pose age, per-tick jitter, mocap position and
  attitude noise, dropped frames, late setpoints, the estimator's forward prediction) and
  ``DroneRanges``: the drone-model randomisation, drawn from the drone profiles in calibration/
  (``drone_ranges``);
- the rules both sides apply, array-generic (numpy arrays or torch tensors, torch never imported
  here): ``frame_age`` (latency plus jitter), ``interpolate_pose`` (a pose between two samples:
  position linear, attitude sign-fixed normalised linear), ``perturb_pose`` (mocap noise).

cfrace.env.race_env.RaceEnv applies them to batches of worlds in training; the dry-run's simulated
motion capture (cfrace.flight.mocap_sim.SimSource) applies the same functions to each frame. The
estimator the policy then reads through is the flight stack's own (cfrace.flight.estimator); the
env reproduces its rules on tensors (velocity from the last two frames, hold of the last pose,
forward prediction) and tests/test_loopmodel.py checks the two agree frame for frame.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np

from cfrace.errors import ConfigError

MOCAP_PERIOD_S = 0.010     #: s, the flight loop's tick: one mocap frame per tick (100 Hz)
MAX_LATENCY_S = 0.060      #: s, the oldest pose age a range may ask for (the loop's stale limit is 0.1 s)

#: Brushless idle: armed motors spin at this many counts and lower commands are floored there
#: (bitcraze/crazyflie-firmware, src/modules/src/power_distribution_quadrotor.c, parameter
#: powerDist.idleThrust; the 2.1 Brushless build sets 7000). Brushed builds idle at 0.
IDLE_THRUST_COUNTS = {"cf21bl": 7000.0}


def _ns(x):
    """numpy or torch, whichever holds x (torch is imported only by callers that pass tensors)."""
    if type(x).__module__.split(".")[0] == "torch":
        import torch
        return torch
    return np


# ---------------------------------------------------------------------------------------------- rules
def frame_age(latency_s, jitter_s, u):
    """Pose age of one frame: the latency plus a uniform jitter of +-jitter_s (u uniform in [0, 1)),
    never negative."""
    age = latency_s + jitter_s * (2.0 * u - 1.0)
    return age * (age > 0)


def interpolate_pose(pa, qa, pb, qb, w):
    """The pose a share ``w`` of the way from (pa, qa) to (pb, qb): position linear, attitude the
    normalised linear blend of the two unit quaternions after flipping qb onto qa's hemisphere.
    Shapes (..., 3), (..., 4) and w broadcastable to (..., 1) (or a float)."""
    xp = _ns(pa)
    dot = (qa * qb).sum(-1, keepdims=True) if xp is np else (qa * qb).sum(-1, keepdim=True)
    qb = qb * (1.0 - 2.0 * (dot < 0.0))
    q = (1.0 - w) * qa + w * qb
    n = (q * q).sum(-1, keepdims=True) if xp is np else (q * q).sum(-1, keepdim=True)
    return (1.0 - w) * pa + w * pb, q / n ** 0.5


def perturb_pose(pos, quat, z_pos, noise_m, z_att=None, att_rad=0.0):
    """Mocap noise on a pose: position + noise_m z_pos (z standard normal, shape of pos); attitude
    turned by the small rotation att_rad z_att (rad, body frame; the first-order quaternion
    [1, v/2], normalised). att_rad 0 or z_att None: the attitude as it is."""
    pos = pos + noise_m * z_pos
    if z_att is None:
        return pos, quat
    xp = _ns(quat)
    h = 0.5 * att_rad * z_att
    hx, hy, hz = h[..., 0], h[..., 1], h[..., 2]
    w, x, y, z = quat[..., 0], quat[..., 1], quat[..., 2], quat[..., 3]
    q = xp.stack([w - x * hx - y * hy - z * hz, x + w * hx + y * hz - z * hy,
                  y + w * hy - x * hz + z * hx, z + w * hz + x * hy - y * hx], -1)
    n = (q * q).sum(-1, keepdims=True) if xp is np else (q * q).sum(-1, keepdim=True)
    return pos, q / n ** 0.5


def body_rates(q_prev, q, dt):
    """Body rates (rad/s) from the rotation between two unit quaternions dt apart, as the pose
    estimator computes them: 2 vec(conj(q_prev) q) / dt (q already on q_prev's hemisphere)."""
    xp = _ns(q)
    pw, px, py, pz = q_prev[..., 0], q_prev[..., 1], q_prev[..., 2], q_prev[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    ex = pw * qx - px * qw - py * qz + pz * qy
    ey = pw * qy + px * qz - py * qw - pz * qx
    ez = pw * qz - px * qy + py * qx - pz * qw
    return xp.stack([ex, ey, ez], -1) * (2.0 / dt)


def rotate_body(q, omega, h):
    """q turned for h s at body rates omega: q exp(omega h / 2), normalised (the estimator's
    forward prediction of the attitude)."""
    xp = _ns(q)
    hv = 0.5 * h * omega
    hx, hy, hz = hv[..., 0], hv[..., 1], hv[..., 2]
    n = (hx * hx + hy * hy + hz * hz) ** 0.5
    safe = n + (n < 1e-12)
    s = xp.sin(safe) / safe
    dw, dx, dy, dz = xp.cos(n), hx * s, hy * s, hz * s
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = xp.stack([w * dw - x * dx - y * dy - z * dz, w * dx + x * dw + y * dz - z * dy,
                  w * dy - x * dz + y * dw + z * dx, w * dz + x * dy - y * dx + z * dw], -1)
    m = (r * r).sum(-1, keepdims=True) if xp is np else (r * r).sum(-1, keepdim=True)
    return r / m ** 0.5


# ---------------------------------------------------------------------------------------------- ranges
def _range(name: str, value, lo: float = 0.0, hi: float = math.inf) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: a range LO,HI, got {value!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise ConfigError(f"{name}: finite numbers, got {a},{b}")
    if a > b:
        raise ConfigError(f"{name}: the range is upside down ({a:g} > {b:g}): LO,HI")
    if a < lo or b > hi:
        raise ConfigError(f"{name}: must lie within [{lo:g}, {hi:g}], got {a:g},{b:g}")
    return a, b


def _prob(name: str, value) -> float:
    p = float(value)
    if not 0.0 <= p <= 1.0:
        raise ConfigError(f"{name}: a probability in [0, 1], got {value!r}")
    return p


@dataclass(frozen=True)
class LoopRanges:
    """What training draws for each drone of each episode (uniform in each range)."""
    latency_s: tuple[float, float] = (0.0, 0.030)     #: pose age (mocap, host, radio), per episode
    jitter_s: float = 0.002                           #: +- this per frame, uniform
    noise_m: tuple[float, float] = (0.0005, 0.003)    #: mocap position noise std, per episode
    att_noise_rad: tuple[float, float] = (0.0, 0.01)  #: mocap attitude noise std, per episode
    drop: tuple[float, float] = (0.0, 0.05)           #: share of frames dropped (the estimator holds), per episode
    late: float = 0.3          #: share of episodes whose setpoint lands one tick (10 ms) late
    comp: float = 0.5          #: share of episodes whose estimator predicts forward by the latency (else not at all)

    def __post_init__(self):
        _range("latency", self.latency_s, 0.0, MAX_LATENCY_S)
        _range("jitter", (0.0, self.jitter_s), 0.0, MOCAP_PERIOD_S / 2)
        _range("mocap noise", self.noise_m, 0.0, 0.05)
        _range("attitude noise", self.att_noise_rad, 0.0, 0.2)
        _range("dropped frames", self.drop, 0.0, 0.5)
        _prob("late setpoints", self.late)
        _prob("latency compensation", self.comp)

    @classmethod
    def parse(cls, **given) -> "LoopRanges":
        """From CLI values (ms, mm, percent are converted by the caller); None keeps a default."""
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in given.items() if v is not None})

    def to_meta(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_meta(cls, meta: dict) -> "LoopRanges":
        names = {f.name for f in fields(cls)}
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in meta.items() if k in names})


@dataclass(frozen=True)
class DroneRanges:
    """Drone-model randomisation around the profile a policy trains on (scales of its nominal values,
    uniform; thrust limits and floors in units of the nominal weight)."""
    thrust_gain: tuple[float, float] = (0.9, 1.1)   #: thrust delivered per thrust commanded (mass, thrust curve)
    thrust_cap_w: tuple[float, float] = (1.9, 2.3)  #: collective thrust limit, weights
    thrust_floor_w: tuple[float, float] = (0.0, 0.0)  #: least collective thrust while armed (idle), weights
    tau_m: tuple[float, float] = (1.0, 1.0)         #: motor time constant, scale
    k_aero: tuple[float, float] = (0.5, 2.0)        #: drag, scale
    kp: tuple[float, float] = (0.85, 1.15)          #: rate PID, scales (inertia enters through them)
    ki: tuple[float, float] = (0.85, 1.15)
    kd: tuple[float, float] = (0.7, 1.2)
    profiles: tuple[str, ...] = ()                  #: the profiles the ranges span (record)

    def __post_init__(self):
        for f in fields(self):
            if f.name != "profiles":
                _range(f.name, getattr(self, f.name), 0.0, 10.0)

    def to_meta(self) -> dict:
        return {k: list(v) for k, v in asdict(self).items()}

    @classmethod
    def from_meta(cls, meta: dict) -> "DroneRanges":
        names = {f.name for f in fields(cls)}
        return cls(**{k: tuple(v) for k, v in meta.items() if k in names})


def drone_ranges(base, profiles) -> DroneRanges:
    """Ranges around ``base`` (the training profile) that span ``profiles`` (DroneProfiles, e.g.
    cf2x_paper and cf21bl from calibration/): each drone's motor time constant from half the fastest
    to 1.15 x the slowest; its thrust limit from 0.9 x the lowest to 1.1 x the highest thrust-to-weight;
    its idle floor from 0 to the highest Brushless idle (IDLE_THRUST_COUNTS through the profile's
    thrust curve); rate-PID scales widened by the spread of the profiles' inertia per unit of
    torque authority (arm x max thrust) as the firmware's gains stay fixed; thrust gain +-10 %
    (mass with battery and markers, thrust-curve fit); drag 0.5-2 x (the paper's range)."""
    all_p = [base, *[p for p in profiles if p.name != base.name]]
    taus = [p.tau_m for p in all_p]
    tw = [p.max_collective_thrust / p.weight for p in all_p]
    idle = [p.thrust_curve.to_newtons(IDLE_THRUST_COUNTS[p.name]) / p.weight
            for p in all_p if p.name in IDLE_THRUST_COUNTS]
    auth = [p.inertia[0] / (p.arm_length * p.max_collective_thrust) for p in all_p]
    spread = max(auth) / min(auth)
    return DroneRanges(
        thrust_gain=(0.9, 1.1),
        thrust_cap_w=(round(0.9 * min(tw), 3), round(1.1 * max(tw), 3)),
        thrust_floor_w=(0.0, round(float(max(idle, default=0.0)), 3)),
        tau_m=(round(0.5 * min(taus) / base.tau_m, 3), round(1.15 * max(taus) / base.tau_m, 3)),
        k_aero=(0.5, 2.0),
        kp=(round(0.85 / spread, 3), round(1.15 * spread, 3)),
        ki=(round(0.85 / spread, 3), round(1.15 * spread, 3)),
        kd=(round(0.7 / spread, 3), round(1.2 * spread, 3)),
        profiles=tuple(p.name for p in all_p))
