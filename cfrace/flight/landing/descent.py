"""Landing instead of dropping: how a drone brakes before the firmware takes over, when it may fly
to its spot, and what its touchdown was. Where it lands: cfrace.flight.landing.spots.

* ``BrakeController``: rate-mode braking from the mocap estimate (the firmware's planner starts its
  moves from rest, so we bring the drone to rest first): the wanted acceleration is
  ``-k_v v`` plus an altitude hold, plus a push away from the other flying drones within ``sep_m``
  (``separation_accel``: drones that raced side by side, or one braking ahead of one still flying,
  otherwise stay in contact while they brake); the push comes first, the braking gets what is left
  of ``accel_max`` sideways; the thrust vector ``m (a + g)`` gives the collective thrust and the
  body z axis it needs, body rates turn the drone towards it.
* ``LandingPilot``: brake -> hold while another drone is in the way -> the firmware's go-to and land.
* ``Touchdown``: from the estimates, the moment a drone reaches the floor, where, and its vertical
  speed then.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from cfrace.drone import GRAVITY
from cfrace.rotations import quat_to_rot
from cfrace.flight.landing.spots import LandingConfig, candidate_spots


def stopping_point(pos, vel, accel: float) -> np.ndarray:
    """Where (3,) a drone at pos with velocity vel stops braking at ``accel`` m/s^2 in a straight line."""
    pos, vel = np.asarray(pos, np.float64), np.asarray(vel, np.float64)
    return pos + vel * (float(np.linalg.norm(vel)) / (2.0 * accel))


def separation_accel(pos, vel, near, sep_m: float, k_sep: float, k_damp: float, a_max: float) -> np.ndarray:
    """m/s^2 (3,), the push of a drone at pos, vel (3,) away from the drones ``near`` ((pos, vel) each)
    closer than ``sep_m``: a spring ``k_sep (sep_m - d)`` plus a damper ``k_damp`` on the speed at which
    they close in, along the line between them, summed and at most ``a_max``."""
    a = np.zeros(3)
    for p, v in near:
        d = pos - np.asarray(p, np.float64)
        dist = float(np.linalg.norm(d))
        if dist >= sep_m:
            continue
        n = d / dist if dist > 1e-6 else np.array([1.0, 0.0, 0.0])
        closing = -float((vel - np.asarray(v, np.float64)) @ n)          # > 0: they come nearer
        a += n * (k_sep * (sep_m - dist) + k_damp * max(closing, 0.0))
    size = float(np.linalg.norm(a))
    return a * (a_max / size) if size > a_max else a


@dataclass
class BrakeController:
    """Rate-mode braking: (estimate) -> (body rates deg/s (3,), collective thrust N)."""

    mass: float                        #: kg
    max_thrust: float                  #: N, the most the drone may command
    k_vel: float = 6.0                 #: 1/s, wanted deceleration per m/s
    accel_max: float = 12.0            #: m/s^2, horizontal (about 50 deg of tilt)
    k_z: float = 4.0                   #: 1/s^2, altitude hold (P on height)
    k_vz: float = 3.0                  #: 1/s, altitude hold (D)
    k_att: float = 15.0                #: 1/s, body rate per rad of tilt error
    rate_max_dps: tuple = (100.0, 100.0, 200.0)   #: deg/s per axis: the profile's (the safety check's limits)
    min_height: float = 0.4            #: m, the altitude held is at least this
    sep_m: float = 0.5                 #: m, other flying drones nearer than this push the drone away ...
    k_sep: float = 40.0                #: 1/s^2, ... by this much per m nearer ...
    k_sep_damp: float = 6.0            #: 1/s, ... plus this much per m/s at which they close in ...
    sep_accel_max: float = 8.0         #: m/s^2, ... at most this (the braking gets the rest of accel_max sideways)
    hold_z: float | None = field(default=None, repr=False)

    def command(self, pos, vel, quat, near=()) -> tuple[np.ndarray, float]:
        """pos, vel (3,) world, quat (4,) wxyz world-from-body, near: (pos, vel) of other flying drones
        -> (p, q, r deg/s, thrust N)."""
        pos, vel = np.asarray(pos, np.float64), np.asarray(vel, np.float64)
        if self.hold_z is None:
            self.hold_z = max(float(pos[2]), self.min_height)
        push = separation_accel(pos, vel, near, self.sep_m, self.k_sep, self.k_sep_damp, self.sep_accel_max) \
            if near else np.zeros(3)
        a = -self.k_vel * vel
        a[2] = self.k_z * (self.hold_z - pos[2]) - self.k_vz * vel[2]
        horiz, room = float(np.linalg.norm(a[:2])), self.accel_max - float(np.linalg.norm(push[:2]))
        if horiz > room:                       # the push first: at speed the braking alone is at accel_max
            a[:2] *= max(room, 0.0) / horiz
        a += push
        f = self.mass * (a + np.array([0.0, 0.0, GRAVITY]))
        f[2] = max(f[2], 0.3 * self.mass * GRAVITY)          # never point the thrust down
        rot = quat_to_rot(quat)
        z_body = rot[:, 2]
        z_des = f / np.linalg.norm(f)
        err_body = rot.T @ np.cross(z_body, z_des)           # axis * sin(angle), body frame
        rates = np.degrees(self.k_att * err_body)
        rates[2] = 0.0
        rmax = np.asarray(self.rate_max_dps, np.float64)
        rates = np.clip(rates, -rmax, rmax)
        thrust = float(np.clip(f @ z_body, 0.0, self.max_thrust))   # the part along the body z axis
        return rates, thrust


@dataclass
class Touchdown:
    """Watches one drone's estimates for its touchdown: the first time its height gets below
    ``ground_z`` + ``tolerance`` while descending or resting."""

    ground_z: float                    #: m, the body's height resting on the floor
    tolerance: float = 0.02            #: m
    t: float | None = None             #: s, when
    place: np.ndarray | None = None    #: (3,) m, where
    vz: float = float("nan")           #: m/s, vertical speed then (negative: down)
    _prev: tuple | None = field(default=None, repr=False)

    def update(self, t: float, pos, vel) -> bool:
        """Feed one estimate; True once the touchdown is found."""
        if self.t is not None:
            return True
        pos = np.asarray(pos, np.float64)
        if pos[2] <= self.ground_z + self.tolerance:
            self.t, self.place = t, pos.copy()
            # the speed just before reaching the floor (the estimate at contact may already be braked)
            self.vz = float(self._prev[1][2]) if self._prev is not None else float(np.asarray(vel)[2])
            return True
        self._prev = (t, np.asarray(vel, np.float64).copy())
        return False

    def as_dict(self) -> dict:
        return {"t": self.t, "place": None if self.place is None else [round(float(v), 4) for v in self.place],
                "vz_mps": None if self.t is None else round(self.vz, 4)}


BRAKE, HOLD, APPROACH, DESCEND, DOWN = "brake", "hold", "approach", "descend", "down"
HARD_TOUCHDOWN_MPS = 0.5   #: m/s down at the floor: above it a touchdown while braking is a crash (docs/flight.md)


@dataclass(frozen=True)
class LandingSetup:
    """What the tick needs to land drones: the track (spots), the brake controller's constants,
    the body's resting height, the manoeuvre's limits and how long a landing may take."""

    track: object
    gates: np.ndarray               #: (G, 4) the track's gates (x, y, z, yaw), for the opponent_down rule
    brake: BrakeController
    ground_z: float
    cfg: LandingConfig = LandingConfig()
    timeout_s: float = 8.0          #: s from the landing's start: then the motors are cut
    gate_half: float = 0.7          #: m, half the gates' outer width (their frames' extent from the centre)
    radius: float = 0.0             #: m, the drone's collision radius

    @classmethod
    def for_race(cls, track, profile, cfg: LandingConfig = LandingConfig()) -> "LandingSetup":
        brake = BrakeController(profile.mass, 0.9 * float(profile.thrust_curve.newtons[-1]),
                                rate_max_dps=LANDING_RATE_FACTOR * np.asarray(profile.max_rates_deg, np.float64))
        candidate_spots(track, cfg)                 # computed now, not in the tick of the first landing
        candidate_spots(track, cfg, True)
        return cls(track, np.asarray(track.gates, np.float64), brake, profile.collision_box[2] / 2.0, cfg,
                   gate_half=track.gate.outer / 2.0, radius=profile.collision_radius)


#: the landing's braking may use this many times the profile's body rates (the racing limit; the
#: firmware's rate controller takes far more): from race speed a drone must tilt back fast to stop
#: inside the arena (tests/test_flight_landing.py)
LANDING_RATE_FACTOR = 3.0


@dataclass
class LandingStep:
    """What the loop does for one landing drone on one tick."""

    rates_dps: np.ndarray | None = None    #: a rate setpoint to send (body rates deg/s) ...
    thrust_n: float = 0.0                  #: ... with this collective thrust (N)
    high_level: list = field(default_factory=list)   #: high-level commands to send, in order: (name, args)
    notify_stop: bool = False              #: then hand control to the high-level commander
    stream_pose: bool = True               #: keep streaming the pose (the firmware's estimator needs it)
    done: bool = False                     #: down: stop the drone (motors off, disarm)


@dataclass
class LandingPilot:
    """One drone's landing: brake (rate setpoints from the estimate) -> hold there while ``may_go``
    says another drone is in the way (at most hold_max_s) -> go-to its spot at ``approach_height_m``
    and land (high-level commander; the hand-over is the go-to first, then notify-stop, so the
    firmware's plan replaces our setpoints without a gap) -> down."""

    brake: BrakeController
    spot: np.ndarray | None           #: (2,) m; None: not chosen yet (it brakes on until it is)
    ground_z: float                   #: m, the body's height resting on the floor
    cfg: LandingConfig = LandingConfig()
    start: np.ndarray | None = None   #: (2,) m, where it was expected to stop: its path to the spot starts there
    phase: str = BRAKE
    t_start: float | None = None
    t_phase_end: float = 0.0
    touchdown: Touchdown | None = None
    #: (pos (3,), spot (2,)) -> the spot to fly to from where the braking ended (None: the spot as chosen)
    respot: object = None
    #: (t) -> may the go-to from where it is to its spot start now? (None: at once)
    may_go: object = None
    held_s: float = 0.0               #: s it held before its go-to
    pos: np.ndarray | None = None     #: (3,) m, the newest estimate it was fed
    hit_floor: bool = False           #: it hit the floor while braking or holding: a crash, not a landing

    def step(self, t: float, pos, vel, quat, near=()) -> LandingStep:
        """The drone's estimate at loop time t (near: (pos, vel) of the other flying drones close to it,
        BrakeController.command) -> what to do now."""
        if self.t_start is None:
            self.t_start = t
            self.touchdown = Touchdown(self.ground_z)
        pos = self.pos = np.asarray(pos, np.float64)
        if self.touchdown.update(t - self.t_start, pos, vel) and self.phase in (BRAKE, HOLD):
            # on the floor before the firmware took over: stop there; faster than a landing's touchdown
            # it fell (a drone resting on the floor when its landing began did not)
            self.phase, self.hit_floor = DOWN, self.touchdown.vz < -HARD_TOUCHDOWN_MPS
            return LandingStep(done=True)
        if self.phase == BRAKE:
            speed = float(np.linalg.norm(vel))
            if self.spot is None or (speed >= self.cfg.brake_done_mps and t - self.t_start < self.cfg.brake_max_s):
                rates, thrust = self.brake.command(pos, vel, quat, near)
                return LandingStep(rates_dps=rates, thrust_n=thrust)
            if self.respot is not None:      # chosen from where it was expected to stop: still reachable?
                self.spot = np.asarray(self.respot(pos, self.spot), np.float64)
            self.phase, self.t_phase_end = HOLD, t + self.cfg.hold_max_s
        if self.phase == HOLD:
            if self.may_go is not None and t < self.t_phase_end and not self.may_go(t):
                rates, thrust = self.brake.command(pos, vel, quat, near)      # hover where it braked
                return LandingStep(rates_dps=rates, thrust_n=thrust)
            self.held_s = t - (self.t_phase_end - self.cfg.hold_max_s)
            w, x, y, z = (float(v) for v in quat)
            yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
            duration = self.goto_s(pos)
            self.phase, self.t_phase_end = APPROACH, t + duration
            goal = {"x": float(self.spot[0]), "y": float(self.spot[1]), "z": self.cfg.approach_height_m,
                    "yaw": yaw, "duration": duration}
            return LandingStep(high_level=[("go_to", goal)], notify_stop=True)
        if self.phase == APPROACH and t >= self.t_phase_end:
            self.phase, self.t_phase_end = DESCEND, t + self.cfg.descent_s
            return LandingStep(high_level=[("land", {"height": self.cfg.land_height_m, "yaw": None,
                                                     "duration": self.cfg.descent_s})])
        if self.phase == DESCEND and t >= self.t_phase_end:
            self.phase = DOWN
            return LandingStep(done=True)
        return LandingStep(done=self.phase == DOWN)

    def goto_s(self, pos) -> float:
        """s, the duration of the go-to from pos (3,) to the spot (about approach_speed_mps, at least 1 s)."""
        return max(1.0, float(np.linalg.norm(self.spot - np.asarray(pos)[:2])) / self.cfg.approach_speed_mps)

    def left_s(self, t: float) -> float:
        """s from loop time t to the end of the drone's move to its spot (its go-to or its descent;
        braking or holding: the go-to as if it started at t). A drone behind its plan flies the rest
        of its go-to no faster than planned."""
        if self.phase == DESCEND:
            return max(self.t_phase_end - t, 0.0)
        if self.phase == APPROACH:
            return max(self.t_phase_end - t, self.goto_s(self.pos))
        return 0.0 if self.phase == DOWN else self.goto_s(self.pos)

    def plan(self, t: float, taus: np.ndarray) -> np.ndarray:
        """Where (K, 3) the drone is expected at loop times t + taus (its newest estimate at t), the
        firmware's moves taken as straight lines at constant speed (left_s to the end)."""
        goal = np.array([*self.spot, self.ground_z if self.phase == DESCEND else self.cfg.approach_height_m])
        goal = self.pos if self.phase == DOWN else goal
        f = np.clip(np.asarray(taus, np.float64) / max(self.left_s(t), 1e-3), 0.0, 1.0)[:, None]
        return self.pos + f * (goal - self.pos)
