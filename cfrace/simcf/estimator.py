"""The simulated Crazyflie's state estimator: position and velocity from the IMU and positioning
measurements, with the firmware Kalman filter's reset, parameters and variance logs.

What it keeps from the firmware's extended Kalman filter (kalman_core.c, estimator_kalman.c,
crtp_localization_service.c): the state after a reset (``kalman.initialX/Y/Z``, position std dev
100 m in x and y, 1 m in z, velocity 0.01 m/s), the process noise added each prediction
(``(pNAcc dt^2 + pNVel dt + pNPos)^2`` on position, ``(pNAcc dt + pNVel)^2`` on velocity),
external position measurements with std dev ``locSrv.extPosStdDev`` (0.01 m), and the logs
``kalman.stateX/Y/Z``, ``statePX/PY/PZ``, ``varX/Y/Z``, ``varPX/PY/PZ``.

What it simplifies: one independent 2-state filter (position, velocity) per world axis,
predicted with the measured specific force rotated by the *estimated* attitude plus accelerometer
noise (so without position measurements it drifts like dead reckoning); velocities and their
variances are world-frame (the firmware's are body-frame).

Attitude (kalman_core.c, kalmanCoreInit and kalmanCoreUpdateWithPose; estimator_kalman.c,
resetEstimation; crtp_localization_service.c, extPoseHandler): the estimate is the true attitude
composed with an error rotation that a perfect gyro keeps constant. A reset sets the attitude to
roll 0, pitch 0, yaw ``kalman.initialYaw``. An external pose's quaternion (or a Lighthouse deck's
attitude) is fused with the weight of a scalar Kalman gain, variance ``locSrv.extQuatStdDev^2``
against the attitude variance (initial 0.01 rad, growing with the gyro noise 0.1 rad/s); so a
wrong quaternion wins and a drone that believes it is upside down or turned flies away. Roll and
pitch errors decay toward level with a 0.5 s time constant (the firmware observes tilt through the
accelerometer and the position measurements); yaw is not observable from positions alone here
(the firmware's filter recovers a small yaw error slowly while accelerating).

Positioning sources: the ground station's external position (CRTP localization, what
``cfrace fly`` streams from mocap), and the simulated drone's own decks: ``lighthouse`` (absolute
position at 50 Hz, 2 mm noise: a Lighthouse deck with base stations set up) and ``flow``
(horizontal velocity and height at 100 Hz: a Flow deck over a textured floor).
"""

from __future__ import annotations

import math

import numpy as np

from cfrace.drone import GRAVITY
from cfrace.rotations import quat_to_rot

DECKS = ("lighthouse", "flow", "ledring")   #: ledring: no measurements, its memories (simcf/memory.py)
DECK_PARAMS = {"lighthouse": "deck.bcLighthouse4", "flow": "deck.bcFlow2", "ledring": "deck.bcLedRing"}
LIGHTHOUSE_PERIOD = 0.02   #: s between Lighthouse position measurements
LIGHTHOUSE_STD = 0.002     #: m, per axis
FLOW_PERIOD = 0.01         #: s between Flow deck measurements
FLOW_STD = 0.05            #: m/s, horizontal velocity from optical flow
RANGE_STD = 0.005          #: m, the deck's height (time-of-flight range to the floor)
ACC_NOISE = 0.05           #: m/s^2, accelerometer white noise, 1 sigma per sample
INITIAL_STD = (100.0, 100.0, 1.0)   #: m, position std dev after a reset
INITIAL_VEL_STD = 0.01     #: m/s
INITIAL_ATT_STD = 0.01     #: rad, attitude std dev after a reset (kalman_core.c, stdDevInitialAttitude_*)
GYRO_NOISE = 0.1           #: rad/s, the attitude variance grows by (GYRO_NOISE dt)^2 (measNoiseGyro_*)
TILT_TAU = 0.5             #: s, time constant of the roll/pitch error's decay toward level
LIGHTHOUSE_ATT_STD = 0.01  #: rad, the Lighthouse deck's attitude measurement

_G = np.array([0.0, 0.0, GRAVITY])


def quat_mul(a, b) -> np.ndarray:
    """Hamilton product of wxyz quaternions a b."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def quat_conj(q) -> np.ndarray:
    return np.array([q[0], -q[1], -q[2], -q[3]], np.float64)


def yaw_quat(yaw: float) -> np.ndarray:
    """wxyz of a rotation by yaw rad about world z."""
    return np.array([math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0)])


def slerp(a, b, t: float) -> np.ndarray:
    """Unit wxyz quaternion a fraction t of the way from a to b (shortest path)."""
    b = np.asarray(b, np.float64)
    d = float(np.dot(a, b))
    if d < 0.0:
        b, d = -b, -d
    if d > 0.9995:
        out = a + t * (b - a)
    else:
        th = math.acos(d)
        out = (math.sin((1.0 - t) * th) * a + math.sin(t * th) * b) / math.sin(th)
    return out / np.linalg.norm(out)


def unit_quat(q) -> np.ndarray | None:
    """q (4,) normalized, or None when it is not finite or has no length."""
    q = np.asarray(q, np.float64)
    n = float(np.linalg.norm(q)) if q.shape == (4,) and np.all(np.isfinite(q)) else 0.0
    return q / n if n > 1e-6 else None


def check_decks(decks) -> tuple[str, ...]:
    """Validate a deck list; ValueError naming the unknown one."""
    decks = tuple(decks)
    for d in decks:
        if d not in DECKS:
            raise ValueError(f"unknown deck {d!r} (known: {', '.join(DECKS)})")
    return decks


class PositionEstimator:
    """Per world axis a Kalman filter on (position m, velocity m/s)."""

    def __init__(self, decks=(), seed: int = 0):
        self.decks = check_decks(decks)
        self.rng = np.random.default_rng(seed)
        self.pos = np.zeros(3)
        self.vel = np.zeros(3)
        self.cov = np.zeros((3, 2, 2))      #: per axis [[var p, cov], [cov, var v]]
        self.updates = 0                    #: measurements fused since the last reset
        self.last_external = None           #: simulated time of the last external position (s)
        self._deck_due = {d: 0.0 for d in self.decks}
        self.q_err = np.array([1.0, 0.0, 0.0, 0.0])   #: estimated attitude = q_err * true attitude
        self.att_var = INITIAL_ATT_STD ** 2           #: rad^2
        self.reset((0.0, 0.0, 0.0))

    def reset(self, initial, yaw: float = 0.0, true_quat=(1.0, 0.0, 0.0, 0.0)) -> None:
        """The firmware's reset: position = initial, velocity 0, large position variance; attitude
        roll 0, pitch 0, yaw rad (kalman.initialYaw) whatever the drone's true attitude true_quat (wxyz)."""
        self.pos = np.asarray(initial, np.float64).copy()
        self.vel = np.zeros(3)
        self.cov = np.zeros((3, 2, 2))
        self.cov[:, 0, 0] = np.square(INITIAL_STD)
        self.cov[:, 1, 1] = INITIAL_VEL_STD ** 2
        self.q_err = quat_mul(yaw_quat(float(yaw)), quat_conj(unit_quat(true_quat)))
        self.att_var = INITIAL_ATT_STD ** 2
        self.updates = 0

    def attitude(self, true_quat) -> np.ndarray:
        """The estimated attitude (wxyz world-from-body) of a drone whose true attitude is true_quat."""
        q = quat_mul(self.q_err, true_quat)
        return q / np.linalg.norm(q)

    def fuse_attitude(self, measured, true_quat, std: float) -> bool:
        """An attitude measurement (wxyz world-from-body) with std dev rad; False when unusable."""
        q = unit_quat(measured)
        if q is None or not (std > 0.0 and math.isfinite(std)):
            return False
        gain = self.att_var / (self.att_var + std * std)
        self.q_err = slerp(self.q_err, quat_mul(q, quat_conj(true_quat)), gain)
        self.att_var *= 1.0 - gain
        return True

    def predict(self, acc: np.ndarray, dt: float, noise_acc: tuple[float, float], noise_vel: float,
                noise_pos: float) -> None:
        """Advance by dt s with the measured world acceleration acc (3,) m/s^2 (noise added here);
        noise_acc = (pNAcc_xy, pNAcc_z)."""
        if dt <= 0.0:
            return
        # the accelerometer's specific force, rotated into the world by the estimated attitude
        a = quat_to_rot(self.q_err) @ (np.asarray(acc, np.float64) + _G) - _G
        a += self.rng.normal(0.0, ACC_NOISE, 3)
        twist = unit_quat([self.q_err[0], 0.0, 0.0, self.q_err[3]])
        if twist is not None:   # roll and pitch errors decay toward level, the yaw error stays
            self.q_err = slerp(self.q_err, twist, min(1.0, dt / TILT_TAU))
        self.att_var += (GYRO_NOISE * dt) ** 2
        self.pos += self.vel * dt + 0.5 * a * dt * dt
        self.vel += a * dt
        f = np.array([[1.0, dt], [0.0, 1.0]])
        for k in range(3):
            na = noise_acc[0] if k < 2 else noise_acc[1]
            c = f @ self.cov[k] @ f.T
            c[0, 0] += (na * dt * dt + noise_vel * dt + noise_pos) ** 2
            c[1, 1] += (na * dt + noise_vel) ** 2
            self.cov[k] = c

    def _update(self, k: int, row: int, value: float, std: float) -> None:
        """Scalar measurement of state ``row`` (0 position, 1 velocity) of axis k."""
        c = self.cov[k]
        s = c[row, row] + std * std
        gain = c[:, row] / s
        state = np.array([self.pos[k], self.vel[k]])
        state = state + gain * (value - state[row])
        self.pos[k], self.vel[k] = state
        self.cov[k] = c - np.outer(gain, c[row, :])
        self.updates += 1

    def external_position(self, pos, std: float, t: float) -> None:
        """A position measurement (3,) m from outside (mocap over CRTP), std dev m."""
        pos = np.asarray(pos, np.float64)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)) or not (std > 0.0 and math.isfinite(std)):
            return
        for k in range(3):
            self._update(k, 0, float(pos[k]), std)
        self.last_external = t

    def decks_measure(self, t: float, true_pos: np.ndarray, true_vel: np.ndarray, true_quat) -> None:
        """The decks' measurements that are due at simulated time t (true state in, noise added).
        The Lighthouse deck measures position and attitude; the Flow deck measures the velocity in
        the frame the drone believes it has (its yaw error rotates it) and the height."""
        for deck in self.decks:
            if t + 1e-9 < self._deck_due[deck]:
                continue
            if deck == "lighthouse":
                noisy = true_pos + self.rng.normal(0.0, LIGHTHOUSE_STD, 3)
                for k in range(3):
                    self._update(k, 0, float(noisy[k]), LIGHTHOUSE_STD)
                half = 0.5 * self.rng.normal(0.0, LIGHTHOUSE_ATT_STD, 3)
                self.fuse_attitude(quat_mul([1.0, *half], true_quat), true_quat, LIGHTHOUSE_ATT_STD)
                self._deck_due[deck] = t + LIGHTHOUSE_PERIOD
            else:
                twist = unit_quat([self.q_err[0], 0.0, 0.0, self.q_err[3]])
                seen = quat_to_rot(twist if twist is not None else [1.0, 0.0, 0.0, 0.0]) @ true_vel
                for k in range(2):
                    self._update(k, 1, float(seen[k] + self.rng.normal(0.0, FLOW_STD)), FLOW_STD)
                # the range to the floor (world z = 0) is the height
                self._update(2, 0, float(true_pos[2] + self.rng.normal(0.0, RANGE_STD)), RANGE_STD)
                self._deck_due[deck] = t + FLOW_PERIOD

    def variances(self) -> tuple[np.ndarray, np.ndarray]:
        """(position variances (3,) m^2, velocity variances (3,) (m/s)^2)."""
        return self.cov[:, 0, 0].copy(), self.cov[:, 1, 1].copy()
