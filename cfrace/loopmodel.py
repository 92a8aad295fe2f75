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
motion capture (cfrace.flight.mocap.simulated.SimSource) applies the same functions to each frame. The
estimator the policy then reads through is the flight stack's own (cfrace.flight.mocap.estimation); the
env reproduces its rules on tensors (velocity from the last two frames, hold of the last pose,
forward prediction) and tests/test_loopmodel.py checks the two agree frame for frame.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np

from cfrace.drone import GRAVITY
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


def predict_commanded(pos, vel, quat, acc, h, lag):
    """Position and velocity of the estimator's latency compensation with the loop's last command:
    a pose h s old (vel a pose difference, which lags it by ``lag`` s) brought to now as the
    command flies it: the commanded collective acceleration ``acc`` (m/s^2) along the pose's body
    z, less gravity, from the velocity of the pose's time (vel + a lag). Shapes (..., 3), (..., 3),
    (..., 4), acc/h/lag broadcastable to (..., 1). Returns (pos, vel). (The attitude turns at the
    measured body rates, rotate_body: in lockstep trials that flew better than the commanded rates,
    which the rate controller follows only with the motors' lag.)"""
    xp = _ns(quat)
    w, x, y, z = quat[..., 0:1], quat[..., 1:2], quat[..., 2:3], quat[..., 3:4]
    cat = np.concatenate if xp is np else xp.cat
    a = cat([2.0 * (x * z + w * y) * acc, 2.0 * (y * z - w * x) * acc,
             (1.0 - 2.0 * (x * x + y * y)) * acc - GRAVITY], -1)
    v0 = vel + a * lag
    return pos + v0 * h + a * (0.5 * h * h), v0 + a * h


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
    comp: float = 0.8          #: share of episodes whose estimator predicts forward by the loop's delay (else not at all)

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
    """Drone-model randomisation across drone profiles. Each drone of an episode is one of
    ``profiles`` (probability ``blend``: a mix of two, weight uniform), its per-profile values
    (scales of the training profile's, thrust in units of the drone's own weight), then jittered
    uniformly by the paper's ranges (drag, rate PID) and the ranges below."""
    profiles: tuple[str, ...] = ()                  #: the profiles spanned, the training profile first
    tau_m: tuple[float, ...] = (1.0,)               #: per profile: motor time constant, scale
    thrust_cap_w: tuple[float, ...] = (2.1,)        #: per profile: collective thrust limit, weights
    thrust_floor_w: tuple[float, ...] = (0.0,)      #: per profile: least collective thrust when armed (idle), weights
    pid: tuple[float, ...] = (1.0,)                 #: per profile: rate-PID authority (inertia per torque), scale
    blend: float = 0.2                              #: share of drones mixed between two profiles
    thrust_gain: tuple[float, float] = (0.9, 1.1)   #: thrust delivered per thrust commanded (mass, thrust curve)
    tau_jitter: tuple[float, float] = (0.8, 1.25)   #: motor time constant, scale on the profile's
    cap_jitter: tuple[float, float] = (0.93, 1.07)  #: thrust limit, scale on the profile's
    floor_jitter: tuple[float, float] = (0.8, 1.2)  #: idle floor, scale on the profile's
    k_aero: tuple[float, float] = (0.5, 2.0)        #: drag, scale (the paper's range)
    kp: tuple[float, float] = (0.85, 1.15)          #: rate PID, scales on the profile's (the paper's ranges)
    ki: tuple[float, float] = (0.85, 1.15)
    kd: tuple[float, float] = (0.7, 1.2)

    def __post_init__(self):
        n = len(self.profiles)
        for name in _PER_PROFILE:
            v = getattr(self, name)
            if len(v) != max(n, 1):
                raise ConfigError(f"drone_ranges.{name}: one value per profile ({max(n, 1)}), got {len(v)}")
            for x in v:
                _range(f"drone_ranges.{name}", (x, x), 0.0, 10.0)
        _prob("drone_ranges.blend", self.blend)
        for name in _JITTER:
            _range(f"drone_ranges.{name}", getattr(self, name), 0.0, 10.0)

    def table(self) -> list[list[float]]:
        """Per profile: [tau_m, thrust_cap_w, thrust_floor_w, pid], the rows a drone is drawn from."""
        return [list(r) for r in zip(*(getattr(self, k) for k in _PER_PROFILE))]

    def to_meta(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_meta(cls, meta: dict) -> "DroneRanges":
        names = {f.name for f in fields(cls)}
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in meta.items() if k in names})


_PER_PROFILE = ("tau_m", "thrust_cap_w", "thrust_floor_w", "pid")
_JITTER = ("thrust_gain", "tau_jitter", "cap_jitter", "floor_jitter", "k_aero", "kp", "ki", "kd")


def idle_floor_w(profile) -> float:
    """A profile's least collective thrust while armed, in its weights (IDLE_THRUST_COUNTS through
    its thrust curve; 0 for brushed builds)."""
    counts = IDLE_THRUST_COUNTS.get(profile.name)
    return 0.0 if counts is None else float(profile.thrust_curve.to_newtons(counts)) / profile.weight


def drone_ranges(base, profiles, blend: float = 0.2) -> DroneRanges:
    """DroneRanges for a policy trained on ``base`` that spans ``profiles`` (DroneProfiles from
    calibration/, e.g. cf21bl): each profile's motor time constant relative to ``base``'s, its
    thrust-to-weight (the limit), its idle floor (idle_floor_w) and its rate-PID authority
    relative to ``base``'s (inertia per unit of torque authority, arm x full thrust, since the
    firmware's gains stay the same); the training profile itself is the first row."""
    all_p = [base, *[p for p in profiles if p.name != base.name]]
    auth = [p.inertia[0] / (p.arm_length * p.max_collective_thrust) for p in all_p]
    return DroneRanges(
        profiles=tuple(p.name for p in all_p),
        tau_m=tuple(round(p.tau_m / base.tau_m, 4) for p in all_p),
        thrust_cap_w=tuple(round(p.max_collective_thrust / p.weight, 4) for p in all_p),
        thrust_floor_w=tuple(round(idle_floor_w(p), 4) for p in all_p),
        pid=tuple(round(auth[0] / a, 4) for a in auth),
        blend=blend)


def training_ranges(loop: dict | None, span_profiles, profile):
    """A training run's LoopRanges (from TrainConfig.loop, plain data) and DroneRanges (around
    ``profile``, spanning the profiles named), None where it has none."""
    from cfrace.drone import load_profile
    ranges = LoopRanges.from_meta(loop) if loop is not None else None
    drone = drone_ranges(profile, [load_profile(p) for p in span_profiles]) if span_profiles else None
    return ranges, drone
