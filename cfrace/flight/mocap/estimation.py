"""State estimation from motion-capture poses: position, velocity and attitude per body.

Per body, every frame that holds its pose:
- reject it as *invalid* if any value is NaN/inf or the quaternion has (near) zero norm;
- reject it as an *outlier* if it moved more than max(max_jump_m, max_speed_mps * dt) since the
  last accepted pose (dt on the frame clock): at 100 Hz that is 0.3 m per frame, after an
  occlusion gap the allowance grows with the top speed. If `reacquire_after` outliers in a row
  agree with each other (the first accepted pose was the glitch, or the body was re-labelled),
  the track restarts at the newest one (counted as *reacquired*);
- otherwise accept it: velocity = finite difference low-passed, v += alpha (v_raw - v) (the first
  difference initialises v); the quaternion is normalised (sign kept continuous), rot from it.

Ages use only the caller's `now` (seconds since the last update that accepted a pose), velocity
uses only frame times, so the frame clock and the loop clock need not be the same clock (replay,
simulation). Between poses the position is predicted forward with the velocity for up to
`predict_s` (default stale_after_s), then held. An estimate older than stale_after_s is not valid.

Latency compensation (`lead_s` > 0, the mocap system's latency): the estimate is predicted forward
by the pose's age plus lead_s, the attitude at the measured body rates. For a body the loop has
told its last command (`command`: the collective acceleration along body z it sent,
cfrace.loopmodel.predict_commanded), position and velocity follow the commanded thrust and gravity
from the velocity of the frame's time (a filtered pose difference lags the frame by
dt (1/alpha - 1/2)), with compensation or without (`prediction`, PREDICTIONS); without a command
(before the first setpoint, while a drone lands on the high-level commander) position goes on at
the velocity.
Plain float64 arithmetic and no randomness: the same frames and times give the same estimates.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np

from cfrace.drone import GRAVITY
from cfrace.flight.mocap.sources import MocapFrame
from cfrace.rotations import rot_wxyz

COUNTERS = ("frames", "occluded", "outliers", "invalid", "stale", "reacquired")


@dataclass
class Estimate:
    pos: np.ndarray     #: (3,) m, world
    vel: np.ndarray     #: (3,) m/s, world
    rot: np.ndarray     #: (3, 3) world from body
    quat: np.ndarray    #: (4,) w, x, y, z, unit norm
    t: float            #: s, frame-clock time of the last accepted pose (nan if none yet)
    age_s: float        #: s, caller-clock time since the last accepted pose (inf if none yet)
    valid: bool         #: a pose was accepted within stale_after_s


def _rotate_body(q: tuple, omega: tuple, h: float) -> tuple:
    """q (w, x, y, z) turned for h s at body rates omega (rad/s): q exp(omega h / 2), normalised."""
    hx, hy, hz = 0.5 * h * omega[0], 0.5 * h * omega[1], 0.5 * h * omega[2]
    n = math.sqrt(hx * hx + hy * hy + hz * hz)
    if n < 1e-12:
        return q
    s = math.sin(n) / n
    dw, dx, dy, dz = math.cos(n), hx * s, hy * s, hz * s
    w, x, y, z = q
    r = (w * dw - x * dx - y * dy - z * dz, w * dx + x * dw + y * dz - z * dy,
         w * dy - x * dz + y * dw + z * dx, w * dz + x * dy - y * dx + z * dw)
    m = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3])
    return (r[0] / m, r[1] / m, r[2] / m, r[3] / m)


def _predict_commanded(p: tuple, v: tuple, q: tuple, acc: float, h: float, lag: float) -> tuple[tuple, tuple]:
    """cfrace.loopmodel.predict_commanded on Python floats (one body per call; tests/test_loopmodel.py
    checks the two agree)."""
    w, qx, qy, qz = q
    ax = 2.0 * (qx * qz + w * qy) * acc
    ay = 2.0 * (qy * qz - w * qx) * acc
    az = (1.0 - 2.0 * (qx * qx + qy * qy)) * acc - GRAVITY
    v0x, v0y, v0z = v[0] + ax * lag, v[1] + ay * lag, v[2] + az * lag
    hh = 0.5 * h * h
    return ((p[0] + v0x * h + ax * hh, p[1] + v0y * h + ay * hh, p[2] + v0z * h + az * hh),
            (v0x + ax * h, v0y + ay * h, v0z + az * h))


#: the flight logs' ``latency_prediction``: how the estimate of a body told its command is predicted.
#: velocity: never from the command (logs before 2026-12-07); commanded: only with latency
#: compensation on; commanded_always: also without (h then only the pose's age since its frame,
#: and the velocity from the frame's time: the filtered pose difference's lag made up for).
PREDICTIONS = ("velocity", "commanded", "commanded_always")
PREDICTION = "commanded_always"   #: today's flights' rule


@dataclass
class _Track:
    """One body's filter state, on plain floats (the 100 Hz tick runs this for every body: Python
    float arithmetic costs a fraction of numpy calls on 3-vectors, the more so with the caches cold
    between ticks; `studies/flight_timing/estimator_ab.py` times the update against another commit's)."""
    pos: tuple                     # (x, y, z) m
    quat: tuple                    # (w, x, y, z), unit
    t: float                       # frame clock of the last accepted pose
    now: float                     # caller clock of the update that accepted it
    vel: tuple = (0.0, 0.0, 0.0)
    omega: tuple = (0.0, 0.0, 0.0)   # body rates, rad/s, from quaternion differences (filtered like vel)
    samples: int = 1
    dt: float = 0.0                # s between the last two accepted poses (frame clock)
    out_pos: tuple | None = None   # last rejected pose, for re-acquisition
    out_t: float = 0.0
    out_run: int = 0


def _dist(a: tuple, b: tuple) -> float:
    dx, dy, dz = a[0] - b[0], a[1] - b[1], a[2] - b[2]
    return math.sqrt(dx * dx + dy * dy + dz * dz)


class PoseEstimator:
    """Per-body estimates from MocapFrames; see the module docstring for the rules."""

    def __init__(self, bodies: list[str], *, alpha: float = 0.5, max_speed_mps: float = 20.0,
                 max_jump_m: float = 0.3, stale_after_s: float = 0.1,
                 predict_s: float | None = None, reacquire_after: int = 5, lead_s: float = 0.0,
                 prediction: str = PREDICTION):
        if not 0.0 < alpha <= 1.0:
            raise ValueError(f"alpha must be in (0, 1], got {alpha}")
        if not 0.0 <= lead_s < 0.1:
            raise ValueError(f"lead_s must be in [0, 0.1) s, got {lead_s}")
        self.lead_s = float(lead_s)
        if prediction not in PREDICTIONS:
            raise ValueError(f"prediction must be one of {', '.join(PREDICTIONS)}, got {prediction!r}")
        self.prediction = prediction   #: a PREDICTIONS rule (replays fly the one of their log's meta)
        #: whether a body's last command predicts its estimate (the rule, decided once)
        self._by_command = prediction == "commanded_always" or (prediction == "commanded" and self.lead_s > 0.0)
        self.bodies = list(bodies)
        self.alpha, self.max_speed_mps, self.max_jump_m = alpha, max_speed_mps, max_jump_m
        self.stale_after_s = stale_after_s
        self.predict_s = stale_after_s if predict_s is None else predict_s
        self.reacquire_after = reacquire_after
        self.counters: dict[str, dict[str, int]] = {b: dict.fromkeys(COUNTERS, 0) for b in bodies}
        self._tracks: dict[str, _Track] = {}
        self._last_frame: tuple[int, float] | None = None
        self._commands: dict[str, float] = {}

    def command(self, body: str, acc: float | None) -> None:
        """The last command sent to ``body``: its collective acceleration (m/s^2 along body z, the
        setpoint's thrust over the drone's mass); None: none (the drone is not on rate setpoints)."""
        if acc is None or not math.isfinite(acc):
            self._commands.pop(body, None)
        else:
            self._commands[body] = float(acc)

    def reset(self) -> None:
        self._tracks.clear()
        self._commands.clear()
        self._last_frame = None
        for c in self.counters.values():
            c.update(dict.fromkeys(COUNTERS, 0))

    def _limit(self, dt: float) -> float:
        return max(self.max_jump_m, self.max_speed_mps * dt)

    def _ingest(self, body: str, pos, quat, t: float, now: float) -> None:
        c = self.counters[body]
        c["frames"] += 1
        # tolist() gives Python floats (float64 values) for any float array, one call per vector
        px, py, pz = pos.tolist() if getattr(pos, "ndim", 0) == 1 else np.ravel(pos).tolist()
        qw, qx, qy, qz = quat.tolist() if getattr(quat, "ndim", 0) == 1 else np.ravel(quat).tolist()
        # a sum is finite iff every term is (no overflow at mocap magnitudes)
        if not math.isfinite(px + py + pz + qw + qx + qy + qz):
            c["invalid"] += 1
            return
        norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if norm < 1e-6:
            c["invalid"] += 1
            return
        p, q = (px, py, pz), (qw / norm, qx / norm, qy / norm, qz / norm)
        tr = self._tracks.get(body)
        if tr is None:
            self._tracks[body] = _Track(p, q, t, now)
            return
        dt = t - tr.t
        if dt <= 0.0:                  # repeated or out-of-order pose: nothing new
            return
        if _dist(p, tr.pos) > self._limit(dt):
            c["outliers"] += 1
            self._outlier(body, tr, p, q, t, now)
        else:
            self._accept(tr, p, q, t, now, dt)

    def _outlier(self, body: str, tr: _Track, p: tuple, q: tuple, t: float, now: float) -> None:
        """A pose too far from the track: remembered; the ``reacquire_after``-th in a row that agree
        with each other restart the track at the newest (velocity from the last two)."""
        if tr.out_pos is not None and t > tr.out_t and _dist(p, tr.out_pos) <= self._limit(t - tr.out_t):
            tr.out_run += 1
        else:
            tr.out_run = 1
        if tr.out_run >= self.reacquire_after:
            d = t - tr.out_t
            vel = ((p[0] - tr.out_pos[0]) / d, (p[1] - tr.out_pos[1]) / d, (p[2] - tr.out_pos[2]) / d)
            self._tracks[body] = _Track(p, q, t, now, vel=vel, samples=2)
            self.counters[body]["reacquired"] += 1
        else:
            tr.out_pos, tr.out_t = p, t

    def _accept(self, tr: _Track, p: tuple, q: tuple, t: float, now: float, dt: float) -> None:
        """An accepted pose ``dt`` s after the last: filtered velocity, sign-continuous quaternion,
        filtered body rates (only used to predict the attitude, ``lead_s`` > 0)."""
        px, py, pz = p
        ox, oy, oz = tr.pos
        rx, ry, rz = (px - ox) / dt, (py - oy) / dt, (pz - oz) / dt
        if tr.samples == 1:
            tr.vel = (rx, ry, rz)
        else:
            a, (vx, vy, vz) = self.alpha, tr.vel
            tr.vel = (vx + a * (rx - vx), vy + a * (ry - vy), vz + a * (rz - vz))
        pw, pqx, pqy, pqz = tr.quat
        if q[0] * pw + q[1] * pqx + q[2] * pqy + q[3] * pqz < 0.0:
            q = (-q[0], -q[1], -q[2], -q[3])
        if self.lead_s > 0.0:
            # body rates from the rotation between the two poses: q_rel = conj(q_prev) q, omega =
            # 2 vec(q_rel) / dt (small angle: 0.1 rad per frame is 0.04 % off)
            qw, qx, qy, qz = q
            ex = pw * qx - pqx * qw - pqy * qz + pqz * qy
            ey = pw * qy + pqx * qz - pqy * qw - pqz * qx
            ez = pw * qz - pqx * qy + pqy * qx - pqz * qw
            w = (2.0 * ex / dt, 2.0 * ey / dt, 2.0 * ez / dt)
            if tr.samples == 1:
                tr.omega = w
            else:
                a, (ox, oy, oz) = self.alpha, tr.omega
                tr.omega = (ox + a * (w[0] - ox), oy + a * (w[1] - oy), oz + a * (w[2] - oz))
        tr.pos, tr.quat, tr.t, tr.now, tr.dt = p, q, t, now, dt
        tr.samples += 1
        tr.out_pos, tr.out_run = None, 0

    def peek(self, frame: MocapFrame | None, now: float) -> dict[str, Estimate]:
        """What update(frame, now) would return, leaving the estimator as it was (the same code
        runs on a copy of the state: the flight loop's warm-up uses it)."""
        tracks, counters, last = self._tracks, self.counters, self._last_frame
        self._tracks = {b: copy.copy(tr) for b, tr in tracks.items()}
        self.counters = {b: dict(c) for b, c in counters.items()}
        self._last_frame = None     # a frame update() has taken runs through the same checks again
        try:
            return self.update(frame, now)
        finally:
            self._tracks, self.counters, self._last_frame = tracks, counters, last

    def update(self, frame: MocapFrame | None, now: float) -> dict[str, Estimate]:
        """Take a new frame (or None when none arrived) at caller time `now` (s); estimates for
        every body (bodies never seen: NaN position, valid False)."""
        if frame is not None and self._last_frame != (frame.seq, frame.t):
            self._last_frame = (frame.seq, frame.t)
            for body in self.bodies:
                pose = frame.poses.get(body)
                if pose is None:
                    self.counters[body]["occluded"] += 1
                else:
                    self._ingest(body, pose.pos, pose.quat, float(frame.t), now)
        return {body: self._estimate(body, now) for body in self.bodies}

    def _estimate(self, body: str, now: float) -> Estimate:
        tr = self._tracks.get(body)
        if tr is None:
            self.counters[body]["stale"] += 1
            return Estimate(pos=np.full(3, np.nan), vel=np.full(3, np.nan), rot=np.eye(3),
                            quat=np.array([1.0, 0.0, 0.0, 0.0]), t=math.nan, age_s=math.inf,
                            valid=False)
        age = max(0.0, now - tr.now)
        valid = age <= self.stale_after_s
        if not valid:
            self.counters[body]["stale"] += 1
        h = min(age, self.predict_s)
        (x, y, z), (vx, vy, vz) = tr.pos, tr.vel
        quat = tr.quat
        if self.lead_s > 0.0:
            h += self.lead_s
            quat = _rotate_body(quat, tr.omega, h)
        acc = self._commands.get(body) if self._by_command and tr.samples > 1 else None
        if acc is not None:
            lag = tr.dt * (1.0 / self.alpha - 0.5)
            (x, y, z), (vx, vy, vz) = _predict_commanded((x, y, z), (vx, vy, vz), tr.quat, acc, h, lag)
        else:
            x, y, z = x + vx * h, y + vy * h, z + vz * h
        return Estimate(pos=np.array((x, y, z)), vel=np.array((vx, vy, vz)),
                        rot=rot_wxyz(*quat), quat=np.array(quat), t=tr.t, age_s=age,
                        valid=valid)


def estimates_to_msg(estimates: dict[str, Estimate]) -> dict:
    """The /estimate flight-log message: {body: {pos, vel, quat, age_s, valid}}."""
    return {b: {"pos": e.pos, "vel": e.vel, "quat": e.quat, "age_s": e.age_s, "valid": e.valid}
            for b, e in estimates.items()}
