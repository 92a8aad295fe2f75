"""The high-level commander's planner (the firmware's crtp_commander_high_level.c and planner.c):
take-off, land, go-to and stop, as smooth 7th-order polynomials in x, y, z and yaw.

Rules kept from the firmware:

* states: idle (at boot and after stop or a finished landing: the commander outputs a stop
  setpoint, motors off), disabled (a low-level setpoint took over: no output), flying, landing;
* take-off only from idle (else refused); land from anything but landing; go-to from anything
  (from disabled or idle it starts at the drone's estimated state, else at the current plan);
* every move is one polynomial piece with zero jerk at both ends, from the start state (position,
  velocity, acceleration; take-off and landing start at rest) to the goal at rest; ``linear``
  go-to's move at constant velocity; yaw takes the shortest way;
* a finished flying plan holds its goal; a finished landing goes idle (motors off);
* group masks: a command with mask 0 is for everyone, else for drones whose mask shares a bit;
* the plan only runs while the drone can fly (armed): commands are refused (EBUSY) otherwise.

Not emulated: uploaded trajectories (memory) and spirals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

IDLE, DISABLED, FLYING, LANDING = "idle", "disabled", "flying", "landing"


def _poly7(x0: float, v0: float, a0: float, x1: float, v1: float, a1: float, duration: float) -> np.ndarray:
    """Coefficients c (8,) of x(t) = sum c_k t^k on [0, duration] with the given position, velocity,
    acceleration at both ends and zero jerk at both ends."""
    t = duration
    rows, rhs = [], []
    for tau, (x, v, a) in ((0.0, (x0, v0, a0)), (t, (x1, v1, a1))):
        for deriv, value in enumerate((x, v, a, 0.0)):
            row = np.zeros(8)
            for k in range(deriv, 8):
                row[k] = math.perm(k, deriv) * tau ** (k - deriv)
            rows.append(row)
            rhs.append(value)
    return np.linalg.solve(np.array(rows), np.array(rhs))


def _eval(c: np.ndarray, t: float, deriv: int) -> float:
    return float(sum(math.perm(k, deriv) * c[k] * t ** (k - deriv) for k in range(deriv, 8)))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass
class Goal:
    """The plan evaluated at one instant."""

    pos: np.ndarray    #: m (3,)
    vel: np.ndarray    #: m/s (3,)
    acc: np.ndarray    #: m/s^2 (3,)
    yaw: float         #: rad
    yaw_rate: float    #: rad/s


class Planner:
    """One drone's high-level commander."""

    def __init__(self):
        self.state = IDLE
        self.group_mask = 0
        self._coeffs: np.ndarray | None = None   # (4, 8): x, y, z, yaw
        self._t0 = 0.0
        self._duration = 0.0

    def in_group(self, mask: int) -> bool:
        return mask == 0 or bool(mask & self.group_mask)

    def _plan(self, start: Goal, goal_pos, goal_yaw: float, duration: float, t: float, end_vel=None) -> None:
        duration = max(float(duration), 1e-3)
        end_vel = np.zeros(3) if end_vel is None else end_vel
        d_yaw = _wrap(goal_yaw - start.yaw)
        yaw_rate_end = d_yaw / duration if end_vel.any() else 0.0
        self._coeffs = np.stack(
            [_poly7(start.pos[k], start.vel[k], start.acc[k], goal_pos[k], end_vel[k], 0.0, duration) for k in range(3)]
            + [_poly7(start.yaw, start.yaw_rate, 0.0, start.yaw + d_yaw, yaw_rate_end, 0.0, duration)])
        self._t0, self._duration = t, duration

    def evaluate(self, t: float) -> Goal | None:
        """The plan at time t (s); None when there is no plan to follow (idle or disabled)."""
        if self.state not in (FLYING, LANDING) or self._coeffs is None:
            return None
        tau = min(max(t - self._t0, 0.0), self._duration)
        if self.state == LANDING and t - self._t0 >= self._duration:
            self.state = IDLE
        vals = [[_eval(c, tau, d) for c in self._coeffs] for d in range(3)]
        return Goal(np.array(vals[0][:3]), np.array(vals[1][:3]), np.array(vals[2][:3]), vals[0][3], vals[1][3])

    @staticmethod
    def at_rest(pos, yaw: float) -> Goal:
        return Goal(np.asarray(pos, np.float64).copy(), np.zeros(3), np.zeros(3), float(yaw), 0.0)

    def takeoff(self, pos, yaw: float, height: float, hover_yaw: float, duration: float, t: float) -> int:
        """From the estimated state at rest to ``height`` (m, absolute) above the same x, y. 0 or 1 (refused)."""
        if self.state != IDLE:
            return 1
        start = self.at_rest(pos, yaw)
        self._plan(start, np.array([start.pos[0], start.pos[1], height]), hover_yaw, duration, t)
        self.state = FLYING
        return 0

    def land(self, pos, yaw: float, height: float, hover_yaw: float, duration: float, t: float) -> int:
        """Down to ``height`` (m, absolute) from where the plan (or the estimate) is, then idle."""
        if self.state == LANDING:
            return 1
        current = self.evaluate(t) if self.state == FLYING else None
        base = current.pos if current is not None else np.asarray(pos, np.float64)
        start = self.at_rest(base, current.yaw if current is not None else yaw)
        self._plan(start, np.array([base[0], base[1], height]), hover_yaw, duration, t)
        self.state = LANDING
        return 0

    def go_to(self, estimate: Goal, relative: bool, linear: bool, goal, yaw: float, duration: float,
              t: float) -> int:
        """To ``goal`` (m (3,), relative to the start if ``relative``) and yaw (rad) in duration s.
        Starts at the current plan, or at ``estimate`` when idle or disabled."""
        start = self.evaluate(t) if self.state == FLYING else None
        if start is None:
            start = estimate
        goal = np.asarray(goal, np.float64) + (start.pos if relative else 0.0)
        yaw = yaw + start.yaw if relative else yaw
        if linear:
            duration = max(float(duration), 1e-3)
            v = (goal - start.pos) / duration
            start = Goal(start.pos, v, np.zeros(3), start.yaw, _wrap(yaw - start.yaw) / duration)
            self._plan(start, goal, yaw, duration, t, end_vel=v)
        else:
            self._plan(start, goal, yaw, duration, t)
        self.state = FLYING
        return 0

    def finished(self, t: float) -> bool:
        """The current move has reached its goal."""
        return self._coeffs is not None and t - self._t0 >= self._duration

    def stop(self) -> None:
        """Motors off (the commander outputs a stop setpoint) until the next command."""
        self.state = IDLE

    def disable(self) -> None:
        """A low-level setpoint took over: forget the plan, output nothing."""
        self.state = DISABLED
