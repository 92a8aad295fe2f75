"""The simulated Crazyflie's state estimator: position and velocity from the IMU and positioning
measurements, with the firmware Kalman filter's reset, parameters and variance logs.

What it keeps from the firmware's extended Kalman filter (kalman_core.c, estimator_kalman.c,
crtp_localization_service.c): the state after a reset (``kalman.initialX/Y/Z``, position std dev
100 m in x and y, 1 m in z, velocity 0.01 m/s), the process noise added each prediction
(``(pNAcc dt^2 + pNVel dt + pNPos)^2`` on position, ``(pNAcc dt + pNVel)^2`` on velocity),
external position measurements with std dev ``locSrv.extPosStdDev`` (0.01 m), and the logs
``kalman.stateX/Y/Z``, ``statePX/PY/PZ``, ``varX/Y/Z``, ``varPX/PY/PZ``.

What it simplifies: one independent 2-state filter (position, velocity) per world axis,
predicted with the true acceleration plus accelerometer noise (so without position measurements
it drifts like dead reckoning); velocities and their variances are world-frame (the firmware's
are body-frame); attitude is the simulator's (a perfect gyro and attitude filter).

Positioning sources: the ground station's external position (CRTP localization, what
``cfrace fly`` streams from mocap), and the simulated drone's own decks: ``lighthouse`` (absolute
position at 50 Hz, 2 mm noise: a Lighthouse deck with base stations set up) and ``flow``
(horizontal velocity and height at 100 Hz: a Flow deck over a textured floor).
"""

from __future__ import annotations

import math

import numpy as np

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
        self.reset((0.0, 0.0, 0.0))

    def reset(self, initial) -> None:
        """The firmware's reset: position = initial, velocity 0, large position variance."""
        self.pos = np.asarray(initial, np.float64).copy()
        self.vel = np.zeros(3)
        self.cov = np.zeros((3, 2, 2))
        self.cov[:, 0, 0] = np.square(INITIAL_STD)
        self.cov[:, 1, 1] = INITIAL_VEL_STD ** 2
        self.updates = 0

    def predict(self, acc: np.ndarray, dt: float, noise_acc: tuple[float, float], noise_vel: float,
                noise_pos: float) -> None:
        """Advance by dt s with the measured world acceleration acc (3,) m/s^2 (noise added here);
        noise_acc = (pNAcc_xy, pNAcc_z)."""
        if dt <= 0.0:
            return
        a = np.asarray(acc, np.float64) + self.rng.normal(0.0, ACC_NOISE, 3)
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

    def decks_measure(self, t: float, true_pos: np.ndarray, true_vel: np.ndarray) -> None:
        """The decks' measurements that are due at simulated time t (true state in, noise added)."""
        for deck in self.decks:
            if t + 1e-9 < self._deck_due[deck]:
                continue
            if deck == "lighthouse":
                noisy = true_pos + self.rng.normal(0.0, LIGHTHOUSE_STD, 3)
                for k in range(3):
                    self._update(k, 0, float(noisy[k]), LIGHTHOUSE_STD)
                self._deck_due[deck] = t + LIGHTHOUSE_PERIOD
            else:
                for k in range(2):
                    self._update(k, 1, float(true_vel[k] + self.rng.normal(0.0, FLOW_STD)), FLOW_STD)
                # the range to the floor (world z = 0) is the height
                self._update(2, 0, float(true_pos[2] + self.rng.normal(0.0, RANGE_STD)), RANGE_STD)
                self._deck_due[deck] = t + FLOW_PERIOD

    def variances(self) -> tuple[np.ndarray, np.ndarray]:
        """(position variances (3,) m^2, velocity variances (3,) (m/s)^2)."""
        return self.cov[:, 0, 0].copy(), self.cov[:, 1, 1].copy()
