"""Landing instead of dropping: where each drone lands, how it brakes before the firmware takes
over, and what its touchdown was.

* ``choose_landing_spots``: per drone a spot on the floor inside the arena, clear of the gates'
  frames, the obstacles and the other drones (their spots and where they are), as near as possible
  to where the drone will have stopped, reachable in a straight line that crosses no gate and no
  obstacle. Greedy in drone order; each spot then blocks the next drones.
* ``BrakeController``: rate-mode braking from the mocap estimate (the firmware's planner starts its
  moves from rest, so we bring the drone to rest first): the wanted acceleration is
  ``-k_v v`` (at most ``accel_max``) plus an altitude hold, the thrust vector ``m (a + g)`` gives the
  collective thrust and the body z axis it needs, body rates turn the drone towards it.
* ``Touchdown``: from the estimates, the moment a drone reaches the floor, where, and its vertical
  speed then.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from cfrace.drone import GRAVITY
from cfrace.flight.estimator import quat_to_rot


@dataclass(frozen=True)
class LandingConfig:
    """Limits of the landing manoeuvre (m, m/s, s)."""

    wall_margin_m: float = 0.5        #: spots this far inside the arena's walls
    gate_clearance_m: float = 0.6     #: from a gate frame's footprint on the floor
    obstacle_clearance_m: float = 0.5  #: from an obstacle's box
    drone_separation_m: float = 0.8   #: between spots, and from other drones
    grid_m: float = 0.1               #: spacing of the candidate spots
    path_clearance_m: float = 0.15    #: the straight path to the spot stays this far from obstacles and gates
    path_separation_m: float = 0.3    #: ... and this far from the other drones' paths and from drones that stay
    max_tries: int = 100              #: nearest free spots whose path is checked; none clear: land where it stops
    approach_height_m: float = 0.25   #: height of the go-to to the spot, before the vertical landing
    approach_speed_mps: float = 1.0   #: mean speed of the go-to (its duration: distance / speed, >= 1 s)
    descent_s: float = 1.5            #: duration of the final land from approach_height_m ...
    land_height_m: float = -0.05      #: ... to this height: below the floor, so that the drone is down
                                      #: (not a few cm up, lagging the plan) when the planner turns the motors off
    brake_done_mps: float = 0.3       #: braking ends below this speed ...
    brake_max_s: float = 1.5          #: ... or after this long


def _seg_point_dist(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Distance of points p (K, 2) to the segment a-b (2,)."""
    d = b - a
    t = np.clip(((p - a) @ d) / max(float(d @ d), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * d), axis=1)


def _segments_cross(p1, p2, q1, q2) -> bool:
    """Do the 2D segments p1-p2 and q1-q2 intersect (touching counts)?"""
    def orient(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    d1, d2 = orient(q1, q2, p1), orient(q1, q2, p2)
    d3, d4 = orient(p1, p2, q1), orient(p1, p2, q2)
    return d1 * d2 <= 0.0 and d3 * d4 <= 0.0


def gate_footprints(track) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each gate's frame seen from above: the segment (2,) - (2,) of its outer width."""
    out = []
    half = track.gate.outer / 2.0
    for x, y, _, yaw in track.gates:
        lateral = np.array([-math.sin(yaw), math.cos(yaw)])
        c = np.array([x, y])
        out.append((c - half * lateral, c + half * lateral))
    return out


def _obstacle_dist(track, pts: np.ndarray) -> np.ndarray:
    """Distance of points (K, 2) to the nearest obstacle box footprint (inf without obstacles)."""
    best = np.full(len(pts), np.inf)
    for o in track.obstacles:
        c, s = math.cos(o.yaw), math.sin(o.yaw)
        rel = pts - np.asarray(o.center, np.float64)
        local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], axis=1)
        outside = np.maximum(np.abs(local) - np.array(o.size[:2]) / 2.0, 0.0)
        best = np.minimum(best, np.linalg.norm(outside, axis=1))
    return best


def _to_segments(start: np.ndarray, ends: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Distance (K,) of the point p (2,) to each segment start-ends[k] (ends (K, 2))."""
    d = ends - start
    t = np.clip(((p - start) @ d.T) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
    return np.linalg.norm(start + t[:, None] * d - p, axis=1)


def _apart(start: np.ndarray, ends: np.ndarray, paths, still, separation: float) -> np.ndarray:
    """(K,) bool: the straight path start-ends[k] keeps ``separation`` from every path (a, b) of
    ``paths`` (other drones flying to their spots at the same time) and from the points ``still``,
    or, where a drone starts nearer than that, no less than at the start (it is where it is)."""
    ok = np.ones(len(ends), bool)
    for q in still:
        q = np.asarray(q, np.float64)[:2]
        ok &= _to_segments(start, ends, q) >= min(separation, float(np.linalg.norm(start - q))) - 1e-9
    for a, b in paths:
        def orient(p, q, r):   # (K,) or scalar: sign of the turn p -> q -> r
            return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])
        cross = ((orient(a, b, start) * orient(a, b, ends) <= 0)
                 & (orient(start, ends, a) * orient(start, ends, b) <= 0))
        at_start = float(_seg_point_dist(a, b, start[None])[0])
        near = np.minimum.reduce([_to_segments(start, ends, a), _to_segments(start, ends, b),
                                  _seg_point_dist(a, b, ends), np.full(len(ends), at_start)])
        ok &= ~cross & (near >= min(separation, at_start) - 1e-9)
    return ok


def path_clear(track, start: np.ndarray, end: np.ndarray, clearance: float) -> bool:
    """The straight path start-end (2,) crosses no gate footprint and keeps ``clearance`` from the gate
    footprints and the obstacles (points of the path already closer at the start do not count: the
    drone is where it is; near a gate the path must lead away from it, not along its frame)."""
    footprints = gate_footprints(track)
    for a, b in footprints:
        if _segments_cross(start, end, a, b) and _seg_point_dist(a, b, start[None])[0] > 1e-6:
            return False
    step = 0.05
    n = max(2, int(np.linalg.norm(end - start) / step) + 1)
    pts = start + np.linspace(0.0, 1.0, n)[:, None] * (end - start)
    gd = np.minimum.reduce([_seg_point_dist(a, b, pts) for a, b in footprints]) if footprints else np.full(n, np.inf)
    leaving = np.diff(gd, prepend=-np.inf) >= 0.5 * float(np.linalg.norm(pts[1] - pts[0]))   # at 30 deg or more
    if not np.all((gd >= clearance) | leaving):
        return False
    if not track.obstacles:
        return True
    d = _obstacle_dist(track, pts)
    start_d = d[0]
    return bool(np.all((d >= clearance) | (d >= start_d - 1e-9)))


@functools.lru_cache(maxsize=8)
def candidate_spots(track, cfg: LandingConfig = LandingConfig()) -> np.ndarray:
    """(K, 2) floor points inside the arena that are clear of gates and obstacles (computed once per
    track and config: a read-only array)."""
    a = track.arena
    xs = np.arange(a.x[0] + cfg.wall_margin_m, a.x[1] - cfg.wall_margin_m + 1e-9, cfg.grid_m)
    ys = np.arange(a.y[0] + cfg.wall_margin_m, a.y[1] - cfg.wall_margin_m + 1e-9, cfg.grid_m)
    pts = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    ok = _obstacle_dist(track, pts) >= cfg.obstacle_clearance_m
    for g0, g1 in gate_footprints(track):
        ok &= _seg_point_dist(g0, g1, pts) >= cfg.gate_clearance_m
    out = pts[ok]
    out.flags.writeable = False
    return out


#: candidate spots a drone's choice looks at first, the nearest to where it stops (the whole arena
#: only when none of them will do): the choice runs in the tick, and on a large arena (the complex
#: track: 15 k candidates) checking every candidate against every other drone's path made the tick in
#: which eight drones start landing overrun the loop (tests/test_flight_landing.py, docs/flight.md)
NEAR_CANDIDATES = 1500


def _nearest(track, stop, cand, order, ok, cfg: LandingConfig):
    """The nearest allowed candidate reachable in a straight line (among the max_tries nearest
    allowed ones: this runs in the tick), or None."""
    near = order[ok[order]][:cfg.max_tries]
    return next((cand[k] for k in near if path_clear(track, stop, cand[k], cfg.path_clearance_m)), None)


def choose_landing_spots(track, stops, others=(), cfg: LandingConfig = LandingConfig(), paths=()) -> np.ndarray:
    """Landing spots (N, 2) for drones expected to stop at ``stops`` (N, 2 or 3) m; ``others`` (M, 2 or 3):
    drones that will not move (e.g. already down) and must be kept clear of; ``paths``: (start, spot)
    of drones flying to their spots already, whose paths the new ones must neither cross nor come
    within path_separation_m of. ValueError if the arena has no free spot left for some drone."""
    stops = np.asarray(stops, np.float64).reshape(-1, np.shape(stops)[-1])[:, :2]
    blocked = [np.asarray(o, np.float64)[:2] for o in others]
    everything = candidate_spots(track, cfg)
    still = list(blocked)
    spots = np.zeros((len(stops), 2))
    paths = [(np.asarray(a, np.float64)[:2], np.asarray(b, np.float64)[:2]) for a, b in paths]   # flown already
    for i, stop in enumerate(stops):
        dist = np.linalg.norm(everything - stop, axis=1)
        near = np.argpartition(dist, NEAR_CANDIDATES)[:NEAR_CANDIDATES] if len(dist) > NEAR_CANDIDATES else None
        pending = blocked + [stops[j] for j in range(i + 1, len(stops))]
        @functools.cache
        def candidates(idx: int) -> tuple:
            """(candidates, nearest first, clear of the pending drones): the nearest ones (0) or all (1)."""
            sel = near if idx == 0 and near is not None else slice(None)
            cand = everything[sel]
            ok = np.ones(len(cand), bool)
            for b in pending:
                ok &= np.linalg.norm(cand - b, axis=1) >= cfg.drone_separation_m
            return cand, np.argsort(dist[sel]), ok

        def nearest(rule) -> np.ndarray | None:
            """The nearest allowed candidate under ``rule`` (cand -> extra mask): among the nearest
            candidates first, then (none of them allowed) the whole arena: the same spot either way."""
            for idx in ((0, 1) if near is not None else (1,)):
                cand, order, clear = candidates(idx)
                ok = clear & rule(cand)
                found = _nearest(track, stop, cand, order, ok, cfg)
                if found is not None or np.count_nonzero(ok) >= cfg.max_tries:
                    return found          # the max_tries nearest allowed ones overall were all looked at
            return None

        # a spot whose path keeps clear of the other drones' paths; else straight down where the drone
        # stops if that is clear of them; else clear of the drones that stay; else merely free
        chosen = nearest(lambda cand: _apart(stop, cand, paths, still, cfg.path_separation_m))
        sep = cfg.path_separation_m
        if chosen is None and paths and all(_seg_point_dist(a, b, stop[None])[0] >= sep for a, b in paths) \
                and all(np.linalg.norm(stop - np.asarray(q)[:2]) >= sep for q in still):
            chosen = stop.copy()
        for rule in (lambda cand: _apart(stop, cand, (), still, cfg.path_separation_m),
                     lambda cand: np.ones(len(cand), bool)):
            if chosen is None:
                chosen = nearest(rule)
        if chosen is None:
            raise ValueError(f"no free landing spot in the arena for drone {i}")
        spots[i] = chosen
        blocked.append(chosen)
        paths.append((stop, chosen))
    return spots


def swap_pays(a, spot_a, b, spot_b, margin: float = 0.05) -> bool:
    """Drones at a and b (2,) fly straight to spot_a and spot_b: are the two paths together at least
    ``margin`` m shorter with the spots swapped? Then the swapped paths do not cross (crossing
    straight paths can always be uncrossed into a shorter pair)."""
    n = np.linalg.norm
    return bool(n(a - spot_b) + n(b - spot_a) + margin < n(a - spot_a) + n(b - spot_b))


def stopping_point(pos, vel, accel: float) -> np.ndarray:
    """Where (3,) a drone at pos with velocity vel stops braking at ``accel`` m/s^2 in a straight line."""
    pos, vel = np.asarray(pos, np.float64), np.asarray(vel, np.float64)
    return pos + vel * (float(np.linalg.norm(vel)) / (2.0 * accel))


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
    hold_z: float | None = field(default=None, repr=False)

    def command(self, pos, vel, quat) -> tuple[np.ndarray, float]:
        """pos, vel (3,) world, quat (4,) wxyz world-from-body -> (p, q, r deg/s, thrust N)."""
        pos, vel = np.asarray(pos, np.float64), np.asarray(vel, np.float64)
        if self.hold_z is None:
            self.hold_z = max(float(pos[2]), self.min_height)
        a = -self.k_vel * vel
        a[2] = self.k_z * (self.hold_z - pos[2]) - self.k_vz * vel[2]
        horiz = float(np.linalg.norm(a[:2]))
        if horiz > self.accel_max:
            a[:2] *= self.accel_max / horiz
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


BRAKE, APPROACH, DESCEND, DOWN = "brake", "approach", "descend", "down"


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
    """One drone's landing: brake (rate setpoints from the estimate) -> go-to its spot at
    ``approach_height_m`` and land (high-level commander; the hand-over is the go-to first, then
    notify-stop, so the firmware's plan replaces our setpoints without a gap) -> down."""

    brake: BrakeController
    spot: np.ndarray                  #: (2,) m
    ground_z: float                   #: m, the body's height resting on the floor
    cfg: LandingConfig = LandingConfig()
    start: np.ndarray | None = None   #: (2,) m, where it was expected to stop: its path to the spot starts there
    phase: str = BRAKE
    t_start: float | None = None
    t_phase_end: float = 0.0
    touchdown: Touchdown | None = None
    #: (pos (3,), spot (2,)) -> the spot to fly to from where the braking ended (None: the spot as chosen)
    respot: object = None
    pos: np.ndarray | None = None     #: (3,) m, the newest estimate it was fed

    def step(self, t: float, pos, vel, quat) -> LandingStep:
        """The drone's estimate at loop time t -> what to do now."""
        if self.t_start is None:
            self.t_start = t
            self.touchdown = Touchdown(self.ground_z)
        pos = self.pos = np.asarray(pos, np.float64)
        self.touchdown.update(t - self.t_start, pos, vel)
        if self.phase == BRAKE:
            speed = float(np.linalg.norm(vel))
            if speed >= self.cfg.brake_done_mps and t - self.t_start < self.cfg.brake_max_s:
                rates, thrust = self.brake.command(pos, vel, quat)
                return LandingStep(rates_dps=rates, thrust_n=thrust)
            if self.respot is not None:      # chosen from where it was expected to stop: still reachable?
                self.spot = np.asarray(self.respot(pos, self.spot), np.float64)
            w, x, y, z = (float(v) for v in quat)
            yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
            duration = max(1.0, float(np.linalg.norm(self.spot - pos[:2])) / self.cfg.approach_speed_mps)
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
