"""Do the poses move with the commands? The check that a pose source belongs to the drones it steers.

A drone in rate mode does, by the drone model (cfrace.sim.dynamics, the firmware's rate loop):
- turn at the body rates it is told, a few ticks late (the rate controller and the rotors);
- accelerate by its collective thrust along its body z axis, minus gravity (drag is small at
  these speeds against thrusts of up to 3 g).

Per drone, while it is not stopped, over the last WINDOW_S (near the floor, any pose of the window
below AIRBORNE_Z_M, only the upward part of the thrust residual counts: the floor holds a drone
up, never down, and turns it in no predictable way):
- rate residual: the mean body rate the poses show (the rotation between the window's first and
  last attitude over its length) against the mean of the rates commanded LAG_S earlier, deg/s;
- thrust residual: the velocity change the poses show against the one the commanded thrusts give
  along the poses' own attitudes (sum of (R e3 T / m - g e3) dt), m/s; its limit grows with the
  commanded thrust impulse (sum of T / m dt): at full thrust and full rates the rotors saturate and
  the drone gets less than it was told, and drag grows with speed.
Either above its limit for MISMATCH_TICKS ticks in a row is a mismatch: the drone is stopped
(safety kind ``pose_mismatch``). Replayed or simulated poses of other drones, or two swapped mocap
bodies, show rates and velocity changes that the commands do not explain. The limits were set
against the shipped policies' races (`python studies/flight/consistency_races.py`: docs/flight.md,
"Poses that do not belong to the drones").
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from cfrace.drone import GRAVITY
from cfrace.errors import MocapError
from cfrace.flight.landing.descent import BRAKE, HOLD

WINDOW_S = 0.1           #: s, the window the residuals average over
LAG_S = 0.02             #: s, commanded rates show in the poses this much later (rate loop + rotors)
AIRBORNE_Z_M = 0.2       #: m, below this the floor may hold the drone: no check
RATE_LIMIT_DPS = 300.0   #: deg/s, mean body-rate residual over the window that counts as a mismatch
DV_LIMIT_MPS = 1.2       #: m/s, velocity-change residual over the window that counts as a mismatch ...
DV_LIMIT_REL = 1.2       #: ... plus this times the commanded thrust impulse over the window (m/s)
MISMATCH_TICKS = 5       #: ticks in a row above a limit before the drone is stopped
STILL_S = 0.3            #: s the poses are watched before take-off
STILL_M = 0.05           #: m a body may move in that time (mocap noise) while its drone is told nothing


def _rotvec(a: tuple, b: tuple) -> tuple[float, float, float]:
    """Body-frame rotation vector (rad) that turns attitude a into b (world-from-body, row-major 9-tuples)."""
    tr = sum(x * y for x, y in zip(a, b))                       # trace of a^T b
    ax = a[2] * b[1] - a[1] * b[2] + a[5] * b[4] - a[4] * b[5] + a[8] * b[7] - a[7] * b[8]
    ay = a[0] * b[2] - a[2] * b[0] + a[3] * b[5] - a[5] * b[3] + a[6] * b[8] - a[8] * b[6]
    az = a[1] * b[0] - a[0] * b[1] + a[4] * b[3] - a[3] * b[4] + a[7] * b[6] - a[6] * b[7]
    angle = math.acos(max(-1.0, min(1.0, (tr - 1.0) / 2.0)))
    s = 2.0 * math.sin(angle)
    k = angle / s if s > 1e-9 else 0.5
    return ax * k, ay * k, az * k


class _Window:
    """One drone's recent poses and commands on plain floats, with the window's sums kept up to date
    as ticks come and go: a few microseconds a drone whatever the window (numpy's per-call cost on
    3-vectors would be most of the tick's)."""

    def __init__(self, w: int, lag: int):
        self.w, self.lag = w, lag
        #: oldest first: (z m, velocity m/s, attitude row-major, commanded body rates rad/s, thrust / m m/s^2)
        self.entries: deque = deque(maxlen=w + lag + 1)
        #: per step of the window: body z axis times the thrust commanded lag ticks before, that thrust,
        #: and the body rates commanded lag ticks before (7 floats), and their sums
        self.steps: deque = deque(maxlen=w)
        self.sums = [0.0] * 7
        self.added = 0                     #: steps added since the last clear

    def clear(self) -> None:
        self.entries.clear()
        self.steps.clear()
        self.sums = [0.0] * 7
        self.added = 0

    def add(self, z: float, vel: tuple, rot: tuple, rates: tuple, accel: float) -> None:
        self.entries.append((z, vel, rot, rates, accel))
        if len(self.entries) <= self.lag:
            return
        _, _, _, (rx, ry, rz), a = self.entries[-1 - self.lag]
        step = (rot[2] * a, rot[5] * a, rot[8] * a, a, rx, ry, rz)
        if len(self.steps) == self.w:
            sums = [s - o + x for s, o, x in zip(self.sums, self.steps[0], step)]
        else:
            sums = [s + x for s, x in zip(self.sums, step)]
        self.steps.append(step)
        self.added += 1
        # summed afresh every window and after a NaN or inf: nothing that has left the window (an
        # enormous value, rounding) stays in the sums
        if self.added % self.w == 0 or not math.isfinite(sum(sums)):
            sums = [sum(col) for col in zip(*self.steps)]
        self.sums = sums

    def residuals(self, dt: float) -> tuple[float, float, float] | None:
        """(rate residual deg/s, velocity-change residual m/s, its limit m/s), or None (too short)."""
        h, w = self.entries, self.w
        if len(h) < h.maxlen:
            return None
        airborne = min(e[0] for e in h) >= AIRBORNE_Z_M
        (_, v1, r1, _, _), (_, v0, r0, _, _) = h[-1], h[-1 - w]
        ex, ey, ez, acc, cx, cy, cz = self.sums
        rate_res = 0.0
        if airborne:
            ox, oy, oz = _rotvec(r0, r1)
            k = w * dt
            rate_res = math.degrees(math.sqrt((ox / k - cx / w) ** 2 + (oy / k - cy / w) ** 2 + (oz / k - cz / w) ** 2))
        dx, dy, dz = v1[0] - v0[0] - ex * dt, v1[1] - v0[1] - ey * dt, v1[2] - v0[2] - (ez - GRAVITY * w) * dt
        dv_res = math.sqrt(dx * dx + dy * dy + dz * dz) if airborne else max(0.0, -dz)
        return rate_res, dv_res, DV_LIMIT_MPS + DV_LIMIT_REL * acc * dt


class ConsistencyMonitor:
    """Per drone (a _Window each): the recent poses and commands, the residuals, and whether they disagree."""

    def __init__(self, n: int, dt: float, mass: float):
        self.dt, self.mass = float(dt), float(mass)
        self.window = max(2, int(round(WINDOW_S / self.dt)))
        self.lag = int(round(LAG_S / self.dt))
        self.hist = [_Window(self.window, self.lag) for _ in range(n)]
        self.over = [0] * n
        self.worst = [[0.0, 0.0] for _ in range(n)]   #: per drone: largest rate residual, dv residual / limit

    def residuals(self, i: int) -> tuple[float, float, float] | None:
        """(rate residual deg/s, velocity-change residual m/s, its limit m/s) of drone i, or None
        (not enough history)."""
        return self.hist[i].residuals(self.dt)

    def update_all(self, drones, ests) -> list[str | None]:
        """update() for every drone of the tick (cfrace.flight.loop.state.FlownDrone): judged while it flies
        on body rates, racing or braking (and holding) before a landing (the high-level commander's moves are not)."""
        on_rates = [d.action is not None if d.landing is None else d.landing.phase in (BRAKE, HOLD) for d in drones]
        return [self.update(i, e, d.rates_dps, d.thrust_n, not d.stopped and r)
                for i, (d, e, r) in enumerate(zip(drones, ests, on_rates))]

    def update(self, i: int, est, rates_dps, thrust_n: float, flying: bool) -> str | None:
        """Add drone i's newest estimate and the command sent with it; a detail text when the poses
        and the commands have disagreed for MISMATCH_TICKS ticks, else None."""
        if not flying or not est.valid:
            self.hist[i].clear()
            self.over[i] = 0
            return None
        r = math.pi / 180.0
        self.hist[i].add(float(est.pos[2]), est.vel.tolist(), np.asarray(est.rot).ravel().tolist(),
                         (float(rates_dps[0]) * r, float(rates_dps[1]) * r, float(rates_dps[2]) * r),
                         float(thrust_n) / self.mass)
        res = self.residuals(i)
        if res is None:
            self.over[i] = 0
            return None
        rate_res, dv_res, dv_limit = res
        worst = self.worst[i]
        worst[0], worst[1] = max(worst[0], rate_res), max(worst[1], dv_res / dv_limit)
        self.over[i] = self.over[i] + 1 if rate_res > RATE_LIMIT_DPS or dv_res > dv_limit else 0
        if self.over[i] >= MISMATCH_TICKS:
            return (f"the poses do not move with the commands: body rates off by {rate_res:.0f} deg/s "
                    f"(limit {RATE_LIMIT_DPS:g}), velocity change off by {dv_res:.2f} m/s (limit {dv_limit:.2f}) "
                    f"over {self.window * self.dt * 1e3:.0f} ms")
        return None


def check_still(mocap, bodies: list[str], seconds: float = STILL_S, clock=None) -> None:
    """Before take-off (the drones lie on the floor and are told nothing): every body's pose must
    stay within STILL_M for ``seconds``; MocapError naming the body otherwise (replayed or simulated
    poses of a flight, or poses of other drones, move)."""
    import time

    clock = clock or time.monotonic
    first: dict = {}
    end = clock() + seconds
    while clock() < end:
        frame = mocap.read(0.02)
        time.sleep(0.01)   # an in-process source answers at once: leave the GIL to the drones' threads
        if frame is None:
            continue
        for b in bodies:
            pose = frame.poses.get(b)
            if pose is None:
                continue
            first.setdefault(b, pose.pos.copy())
            moved = float(np.linalg.norm(pose.pos - first[b]))
            if not moved <= STILL_M:
                raise MocapError(f"mocap body {b} moved {moved:.2f} m in {seconds:g} s before take-off while its "
                                 f"drone was told nothing: these poses do not belong to the drones that would fly")
