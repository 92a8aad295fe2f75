"""The high-level commander's planner (the firmware's crtp_commander_high_level.c and planner.c):
take-off, land, go-to, spiral and stop, as smooth 7th-order polynomials in x, y, z and yaw, and the
trajectories uploaded to its memory.

Rules kept from the firmware:

* states: idle (at boot and after stop or a finished landing: the commander outputs a stop
  setpoint, motors off), disabled (a low-level setpoint took over: no output), flying, landing;
* take-off only from idle (else refused); land from anything but landing; go-to from anything
  (from disabled or idle it starts at the drone's estimated state, else at the current plan);
* every move is one polynomial piece with zero jerk at both ends, from the start state (position,
  velocity, acceleration; take-off and landing start at rest) to the goal at rest; ``linear``
  go-to's move at constant velocity; yaw takes the shortest way;
* a finished flying plan holds its goal; a finished landing goes idle (motors off);
* group masks (hlCommander.groupmask): a command with mask 0 is for everyone, else for drones in a group of the mask;
* the plan only runs while the drone can fly (armed): commands are refused (EBUSY) otherwise;
* trajectories uploaded to the trajectory memory (4096 bytes, 31 definitions): define_trajectory
  stores a definition (crtp_commander_high_level.c define_trajectory: only the id is checked, ENOEXEC
  at 31 and above); start_trajectory flies it from now (plain poly4d: relative position and yaw,
  reversed, time scale; compressed: relative position only, ENOEXEC with a time scale other than 1
  or reversed), an undefined id is ignored with answer 0; a trajectory that evaluates to NaN disables
  the commander (no more setpoints: the last one ages into the watchdog), as the firmware's
  crtpCommanderHighLevelGetSetpoint does;
* spiral (planner.c plan_spiral_from): one 7th-order piece along an arc of growing or shrinking radius
  that climbs linearly, heading along it (or sideways), the angle clamped to +-2 pi, radii to >= 0.

Every move is a `cfrace.simcf.trajectory.PiecewiseTrajectory`: one evaluator for all of them.
Where the simulator refuses what the firmware would fly from beyond its trajectory memory (a
definition past the memory's end, a compressed trajectory without its end marker) it answers
ENOEXEC and says so on the console.
"""

from __future__ import annotations

import errno
import math

import numpy as np

from cfrace.simcf.trajectory import (POLY4D_BYTES, Goal, Piece, PiecewiseTrajectory, Poly4dMemory, _wrap,  # noqa: F401
                                     decode_compressed, single_piece)

IDLE, DISABLED, FLYING, LANDING = "idle", "disabled", "flying", "landing"
TRAJECTORY_MEMORY_SIZE = 4096     #: bytes (crtp_commander_high_level.c TRAJECTORY_MEMORY_SIZE)
NUM_TRAJECTORY_DEFINITIONS = 31   #: trajectory ids 0..30
LOCATION_MEM = 1                  #: a trajectory in the trajectory memory (the only location)
POLY4D, POLY4D_COMPRESSED = 0, 1  #: trajectory types


def in_group(mask: int, group_mask: int) -> bool:
    """A command with ``mask`` is for this drone (hlCommander.groupmask ``group_mask``): mask 0 is for
    everyone, else for drones whose groups share a bit (crtp_commander_high_level.c isInGroup)."""
    return mask == 0 or bool(mask & group_mask)


class Planner:
    """One drone's high-level commander, with its trajectory memory and definitions (RAM: a reboot,
    which makes a new Planner, clears them)."""

    def __init__(self):
        self.state = IDLE
        self.traj: PiecewiseTrajectory | None = None
        self.memory = bytearray(TRAJECTORY_MEMORY_SIZE)   #: the trajectory memory (MEM_TYPE_TRAJ)
        self.definitions: list = [None] * NUM_TRAJECTORY_DEFINITIONS   #: (location, type, offset, pieces)
        self.events: list[str] = []   #: console lines not yet sent

    def _plan(self, start: Goal, goal_pos, goal_yaw: float, duration: float, t: float, end_vel=None) -> None:
        duration = max(float(duration), 1e-3)
        end_vel = np.zeros(3) if end_vel is None else end_vel
        d_yaw = _wrap(goal_yaw - start.yaw)
        yaw_rate_end = d_yaw / duration if end_vel.any() else 0.0
        end = Goal(np.asarray(goal_pos, np.float64), end_vel, np.zeros(3), start.yaw + d_yaw, yaw_rate_end)
        self.traj = single_piece(start, end, duration, t)

    def evaluate(self, t: float) -> Goal | None:
        """The plan at time t (s); None when there is no plan to follow (idle or disabled, or the plan
        evaluated to NaN: then disabled, as the firmware)."""
        if self.state not in (FLYING, LANDING) or self.traj is None:
            return None
        if self.state == LANDING and self.traj.finished(t):
            self.state = IDLE
        goal = self.traj.eval(t)
        if not goal.finite():
            self.state = DISABLED
            self.events.append("HL: the trajectory evaluates to NaN/inf: high-level commander disabled, "
                               "no more setpoints from it")
            return None
        return goal

    def current(self, t: float, estimate: Goal) -> Goal:
        """The firmware's "last setpoint" that new plans start from: the plan while it runs, else the estimate."""
        goal = self.evaluate(t) if self.state in (FLYING, LANDING) else None
        return estimate if goal is None else goal

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

    def spiral(self, start: Goal, sideways: bool, clockwise: bool, angle: float, r0: float, rf: float,
               ascent: float, duration: float, t: float) -> int:
        """An arc of ``angle`` rad (clamped to +-2 pi) from radius r0 to rf (m, >= 0), climbing ``ascent``
        m, in duration s, from ``start`` (its position and yaw; planner.c plan_spiral_from). The drone
        heads along the arc (``sideways``: the arc's centre is ahead of it); ``clockwise`` seen from above."""
        if abs(angle) > 2.0 * math.pi:
            angle = math.copysign(2.0 * math.pi, angle)
            self.events.append(f"HL: spiral angle saturated at {'-' if angle < 0 else ''}2pi")
        if r0 < 0.0 or rf < 0.0:
            r0, rf = max(r0, 0.0), max(rf, 0.0)
            self.events.append("HL: spiral radius set to 0 (was negative)")
        duration = max(float(duration), 1e-3)
        sense = 1.0 if clockwise else -1.0
        omz = -sense * angle / duration              # yaw rate, rad/s
        dr = (rf - r0) / duration                    # radius rate, m/s
        yaw0 = _wrap(start.yaw)
        yaw1 = yaw0 - sense * angle

        def arc(r: float, psi: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            """Offset from the centre, its velocity and acceleration at radius r, heading psi."""
            c, s = math.cos(psi), math.sin(psi)
            u = np.array([-c, -s]) if sideways else np.array([-s, c])     # centre -> drone, unit
            du = np.array([s, -c]) if sideways else np.array([-c, -s])    # d u / d psi
            return (sense * r * u, sense * (dr * u + r * omz * du),
                    sense * (2.0 * dr * omz * du - r * omz * omz * u))

        p0, _, _ = arc(r0, yaw0)
        centre = np.asarray(start.pos[:2], np.float64) - p0
        ends = []
        for r, psi, z in ((r0, yaw0, start.pos[2]), (rf, yaw1, start.pos[2] + ascent)):
            p, v, a = arc(r, psi)
            ends.append(Goal(np.array([*(centre + p), z]), np.array([*v, ascent / duration]),
                             np.array([*a, 0.0]), psi, omz))
        self.traj = single_piece(ends[0], ends[1], duration, t)
        self.state = FLYING
        return 0

    # ------------------------------------------------------------ uploaded trajectories
    def define_trajectory(self, trajectory_id: int, location: int, kind: int, offset: int, n_pieces: int) -> int:
        """Store a definition (crtp_commander_high_level.c define_trajectory). 0, or ENOEXEC for an id >= 31."""
        if not 0 <= trajectory_id < NUM_TRAJECTORY_DEFINITIONS:
            self.events.append(f"HL: define_trajectory: no trajectory id {trajectory_id} (0-"
                               f"{NUM_TRAJECTORY_DEFINITIONS - 1}), ENOEXEC")
            return errno.ENOEXEC
        self.definitions[trajectory_id] = (int(location), int(kind), int(offset), int(n_pieces))
        if kind == POLY4D and offset + n_pieces * POLY4D_BYTES > TRAJECTORY_MEMORY_SIZE:
            self.events.append(f"HL: trajectory {trajectory_id}: {n_pieces} pieces at offset {offset} reach past the "
                               f"{TRAJECTORY_MEMORY_SIZE}-byte trajectory memory; starting it will be refused")
        return 0

    def start_trajectory(self, start: Goal, trajectory_id: int, timescale: float, relative_position: bool,
                         relative_yaw: bool, reversed: bool, t: float) -> int:
        """Fly a defined trajectory from t (crtp_commander_high_level.c start_trajectory2, planner.c
        plan_start_trajectory / plan_start_compressed_trajectory). ``start``: where relative ones begin."""
        d = self.definitions[trajectory_id] if 0 <= trajectory_id < NUM_TRAJECTORY_DEFINITIONS else None
        if d is None or d[0] != LOCATION_MEM or d[1] not in (POLY4D, POLY4D_COMPRESSED):
            self.events.append(f"HL: start_trajectory: trajectory {trajectory_id} is not defined, ignored")
            return 0
        _, kind, offset, n_pieces = d
        if kind == POLY4D:
            if n_pieces < 1 or offset + n_pieces * POLY4D_BYTES > TRAJECTORY_MEMORY_SIZE:
                self.events.append(f"HL: start_trajectory: trajectory {trajectory_id} ({n_pieces} pieces at offset "
                                   f"{offset}) is not inside the trajectory memory, refused (ENOEXEC)")
                return errno.ENOEXEC
            traj = PiecewiseTrajectory(Poly4dMemory(self.memory, offset, n_pieces), t, timescale, reversed)
            if relative_position:
                init = traj.start_point()
                traj.shift = np.asarray(start.pos, np.float64) - init.pos
                if relative_yaw:
                    traj.shift_yaw = _wrap(_wrap(start.yaw) - _wrap(init.yaw))
        else:
            if timescale != 1.0 or reversed:
                self.events.append("HL: start_trajectory: a compressed trajectory runs only forward at time "
                                   "scale 1, ENOEXEC")
                return errno.ENOEXEC
            try:
                pieces = decode_compressed(self.memory, offset)
            except ValueError as e:
                self.events.append(f"HL: start_trajectory: {e}, refused (ENOEXEC)")
                return errno.ENOEXEC
            traj = PiecewiseTrajectory(pieces, t)
            if relative_position:
                traj.shift = np.asarray(start.pos, np.float64) - traj.start_point().pos
        self.traj = traj
        self.state = FLYING
        return 0

    def finished(self, t: float) -> bool:
        """The current move has reached its goal."""
        return self.traj is not None and self.traj.finished(t)

    def stop(self) -> None:
        """Motors off (the commander outputs a stop setpoint) until the next command."""
        self.state = IDLE

    def disable(self) -> None:
        """A low-level setpoint took over: forget the plan, output nothing."""
        self.state = DISABLED

    def drain(self) -> list[str]:
        out, self.events = self.events, []
        return out
