"""The safety check: a PURE function run every tick before anything is sent.

Inputs: per-drone estimates, observations and actions, link states, the tick's timing, the
operator's kill request, and the limits (SafetyConfig + the fence). Output: one Decision naming
the drones to stop and every violation found. It keeps no state; the loop makes stops sticky
and logs each violation once per episode (see loop.py).

Which event stops what (docs/flight.md explains why):

| kind          | scope     | trigger                                                           |
|---------------|-----------|-------------------------------------------------------------------|
| geofence      | one drone | position outside the arena grown by geofence_margin_m             |
| floor         | one drone | z < floor_z_m after floor_grace_s (the training crash rule)       |
| tilt          | one drone | body z axis more than tilt_max_deg from world up                  |
| speed         | one drone | estimated speed > speed_max_mps                                   |
| mocap_stale   | one drone | its pose estimate is invalid or older than mocap_stale_s          |
| non_finite    | one drone | NaN/inf in its estimate, observation or action                    |
| command       | one drone | the setpoint about to be sent is non-finite or beyond the drone   |
|               |           | profile's body rates / the uint16 thrust counts (CommandLimits)   |
| pose_mismatch | all       | a drone's poses do not move with its commands (consistency.py):   |
|               |           | the pose source does not belong to the drones (swap, replay)      |
| link_lost     | one drone | its link reports disconnected or silent for link_timeout_s        |
| gate_crash    | one drone | it crossed its target gate's plane in the frame (a crash)         |
| loop_overrun  | all       | a tick started later than overrun_stop_s after its deadline       |
| operator_kill | all       | Ctrl-C / SIGTERM / the `kill` request                             |
| tick_skipped  | none      | a tick started more than one period late (missed ticks, skipped)  |
| mocap_dropout | none      | no fresh pose for more than 2 ticks but still below mocap_stale_s |

Soft failsafes land the drone instead (the firmware's high-level commander, cfrace.flight.landing.descent):

| kind           | scope     | trigger                                                          |
|----------------|-----------|------------------------------------------------------------------|
| fence_near     | one drone | inside the fence but within fence_soft_m of it                   |
| mocap_degraded | one drone | mocap_glitches pose dropouts (>= 50 ms) / outliers within 2 s    |
| opponent_down  | one drone | a stopped drone within opponent_clearance_m of its path to its   |
|                |           | next gate                                                        |
| low_battery    | one drone | pm.vbat below low_battery_v for low_battery_s                    |
| operator_land  | all       | the operator's "land now" (SIGUSR1)                              |

low_battery and operator_land may start the landing up to 1 s later, where braking at once would
take the drone out of the fence or into a gate (cfrace.flight.safety.failsafe.may_start_landing).
A landing drone is exempt from the racing rules (floor, gate_crash, the soft rules) and from the
profile's command limits (the landing controller bounds its own commands); every hard rule still
cuts its motors.

One-drone events stop only that drone: each drone has its own radio, pose and policy, and the
other drone can finish the race (a stopped drone lies on the floor). Events that say the loop
itself is unhealthy (overrun, operator) stop every drone.

A swarm (N drones) keeps the same rule, written down (docs/flight.md, "Swarm safety"): a drone that
breaches the fence, loses its link or crashes is stopped alone, the others race on (their
policies see it only as long as no live drone is nearer, cfrace.contract.observations); loop and
operator events stop all. Separation (``too_close``, SafetyConfig.min_separation_m): before
take-off the runner refuses to start when two drones stand closer than that on the first mocap
frame (nothing is sent to any drone), and when the loop ends (after the landings) it records the
pairs that were closer than that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from cfrace.contract.actions import THRUST_MAX_COUNTS
from cfrace.flight.config import SafetyConfig

STOP_DRONE, STOP_ALL, NONE = "stop_drone", "stop_all", "none"
LAND_DRONE, LAND_ALL = "land_drone", "land_all"


def too_close(positions: dict, min_m: float) -> list[tuple[str, str, float]]:
    """(name, name, distance m) of every pair of drones closer than ``min_m``; positions: name ->
    (3,) m. Non-finite positions are skipped (the mocap rules handle them)."""
    names = [n for n, p in positions.items() if np.isfinite(np.asarray(p, dtype=np.float64)).all()]
    out = []
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            d = float(np.linalg.norm(np.asarray(positions[names[a]], float) - np.asarray(positions[names[b]], float)))
            if d < min_m:
                out.append((names[a], names[b], round(d, 3)))
    return out


@dataclass(frozen=True)
class Fence:
    """Axis-aligned box the drones must stay in (m); the floor is handled by the floor rule."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    @classmethod
    def from_track(cls, track, margin_m: float) -> "Fence":
        a = track.arena
        return cls((a.x[0] - margin_m, a.y[0] - margin_m, -math.inf),
                   (a.x[1] + margin_m, a.y[1] + margin_m, a.z_max + margin_m))

    def contains(self, pos) -> bool:
        return all(lo <= float(p) <= hi for lo, p, hi in zip(self.lo, pos, self.hi))


@dataclass(frozen=True)
class CommandLimits:
    """What a setpoint sent to a drone may hold: body rates within the drone profile's (deg/s,
    each axis) and thrust counts within the CRTP packet's uint16."""

    max_rates_dps: tuple[float, float, float]
    max_counts: int = THRUST_MAX_COUNTS

    @classmethod
    def from_profile(cls, profile) -> "CommandLimits":
        return cls(tuple(float(v) for v in profile.max_rates_deg))

    def problem(self, command) -> str | None:
        """None if the command (p, q, r deg/s, thrust counts) may be sent, else what is wrong."""
        *rates, counts = command
        if not all(math.isfinite(float(r)) and abs(float(r)) <= m * (1 + 1e-9) for r, m in zip(rates, self.max_rates_dps)):
            return (f"body rates ({', '.join(f'{float(r):g}' for r in rates)}) deg/s beyond the drone's "
                    f"({', '.join(f'{m:g}' for m in self.max_rates_dps)})")
        if not (isinstance(counts, int) and 0 <= counts <= self.max_counts):
            return f"thrust {counts!r} counts outside 0..{self.max_counts}"
        return None


class DroneInputs(NamedTuple):
    """What the safety check sees of one drone this tick (SI units, world frame). A NamedTuple:
    immutable like a frozen dataclass, and built every tick at a fraction of its cost."""

    pos: np.ndarray            #: (3,) m
    vel: np.ndarray            #: (3,) m/s
    rot: np.ndarray            #: (3, 3) world-from-body
    est_valid: bool            #: the estimator has a usable pose
    est_age_s: float           #: s since the last mocap pose of this body
    obs: np.ndarray | None     #: (D,) this tick's observation (None if none computed this tick)
    action: np.ndarray | None  #: (4,) the action about to be sent
    link_connected: bool
    link_rx_age_s: float       #: s since the last packet from the drone
    gate_crash: bool = False   #: crossed the target gate plane inside the frame this tick
    command: tuple | None = None   #: (p, q, r deg/s, thrust counts) about to be sent, None if none
    pose_mismatch: str | None = None   #: why its poses do not move with its commands (consistency.py)
    landing: bool = False      #: the drone is landing (racing and soft rules off)
    mocap_glitches: int = 0    #: pose dropouts and outliers of this body within the last 2 s
    blocked: str = ""          #: what lies in its way to the next gate (a downed drone), "" if nothing
    vbat: float = math.nan     #: V, the drone's battery (nan: unknown)
    vbat_low_s: float = 0.0    #: s its battery has been below low_battery_v without a break


class SafetyInputs(NamedTuple):
    t: float                        #: s since the race start
    dt: float                       #: s, loop period
    tick_late_s: float              #: s, how late this tick started against its deadline
    drones: tuple[DroneInputs, ...]
    operator_kill: str | None = None  #: e.g. "SIGTERM", "SIGINT", or None
    operator_land: str | None = None  #: e.g. "SIGUSR1": land every drone


@dataclass(frozen=True)
class Violation:
    kind: str
    drone: int | None   #: index, or None for the whole loop
    action: str         #: "stop_drone", "stop_all" or "none"
    detail: str


class Decision(NamedTuple):
    stop: tuple[bool, ...]        #: per drone: must be stopped now
    stop_all: bool
    violations: tuple[Violation, ...]
    land: tuple[bool, ...] = ()   #: per drone: must land now (unless stopped)

    @property
    def ok(self) -> bool:
        return not any(self.stop) and not self.stop_all


def _finite(x) -> bool:
    # one sum instead of isfinite().all(): a sum is finite iff every element is (float64 sums of
    # float32 or pose values cannot overflow); Python's sum over tolist() costs a third of numpy's
    # reduction on these few elements (0.5-2 us against 2-3 us a call here, five calls a drone a tick)
    if x is None:
        return True
    return math.isfinite(sum(x.ravel().tolist() if isinstance(x, np.ndarray) else np.ravel(x).tolist()))


def check_drone(i: int, d: DroneInputs, t: float, dt: float, fence: Fence, cfg: SafetyConfig,
                limits: CommandLimits | None = None) -> list[Violation]:
    """All violations of drone i (pure)."""
    out: list[Violation] = []

    def bad(kind: str, detail: str, action: str = STOP_DRONE):
        out.append(Violation(kind, i, action, detail))

    pos_ok, vel_ok, rot_ok = _finite(d.pos), _finite(d.vel), _finite(d.rot)
    if not (pos_ok and vel_ok and rot_ok and _finite(d.obs) and _finite(d.action)):
        parts = [name for name, x in (("estimate", d.pos), ("velocity", d.vel), ("attitude", d.rot),
                                      ("observation", d.obs), ("action", d.action)) if not _finite(x)]
        bad("non_finite", f"NaN/inf in {', '.join(parts)}")
    if limits is not None and d.command is not None:
        problem = limits.problem(d.command)
        if problem is not None:
            bad("command", f"setpoint not sent: {problem}")
    if d.pose_mismatch:   # the pose source does not belong to the drones (a swap, a replay): all of them
        bad("pose_mismatch", d.pose_mismatch, STOP_ALL)
    if not d.est_valid or not (d.est_age_s <= cfg.mocap_stale_s):
        bad("mocap_stale", f"no valid pose for {d.est_age_s * 1e3:.0f} ms (limit {cfg.mocap_stale_s * 1e3:.0f} ms)")
    elif d.est_age_s > 2.5 * dt:
        bad("mocap_dropout", f"pose {d.est_age_s * 1e3:.0f} ms old, riding through", NONE)
    if not d.link_connected:
        bad("link_lost", "link disconnected")
    elif not (d.link_rx_age_s <= cfg.link_timeout_s):
        bad("link_lost", f"no packet for {d.link_rx_age_s * 1e3:.0f} ms (limit {cfg.link_timeout_s * 1e3:.0f} ms)")
    if d.gate_crash and not d.landing:
        bad("gate_crash", "crossed the target gate plane inside the frame")
    if pos_ok:
        x, y, z = float(d.pos[0]), float(d.pos[1]), float(d.pos[2])
        lo, hi = fence.lo, fence.hi
        if not (lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and lo[2] <= z <= hi[2]):
            bad("geofence", f"position ({x:.2f}, {y:.2f}, {z:.2f}) m outside the fence "
                            f"x {lo[0]:.2f}..{hi[0]:.2f}, y {lo[1]:.2f}..{hi[1]:.2f}, z <= {hi[2]:.2f}")
        elif not d.landing:
            room = min(x - lo[0], hi[0] - x, y - lo[1], hi[1] - y, hi[2] - z)
            if room < cfg.fence_soft_m:
                bad("fence_near", f"{room:.2f} m from the fence (soft limit {cfg.fence_soft_m} m): landing", LAND_DRONE)
        if t > cfg.floor_grace_s and z < cfg.floor_z_m and not d.landing:
            bad("floor", f"z {z:.2f} m below {cfg.floor_z_m} m after take-off")
    if not d.landing:
        if d.mocap_glitches >= cfg.mocap_glitches > 0:
            bad("mocap_degraded", f"{d.mocap_glitches} pose dropouts/outliers within 2 s: landing", LAND_DRONE)
        if d.blocked:
            bad("opponent_down", f"{d.blocked} in the way: landing", LAND_DRONE)
        if cfg.low_battery_v > 0 and d.vbat < cfg.low_battery_v and d.vbat_low_s >= cfg.low_battery_s:
            bad("low_battery", f"battery {d.vbat:.2f} V < {cfg.low_battery_v} V for {d.vbat_low_s:.1f} s: landing",
                LAND_DRONE)
    if rot_ok:
        cos_tilt = max(-1.0, min(1.0, float(d.rot[2][2])))  # world z of the body z axis
        if cos_tilt < math.cos(math.radians(cfg.tilt_max_deg)):
            bad("tilt", f"tilt {math.degrees(math.acos(cos_tilt)):.1f} deg > {cfg.tilt_max_deg:g} deg")
    if vel_ok:
        vx, vy, vz = float(d.vel[0]), float(d.vel[1]), float(d.vel[2])
        speed = math.sqrt(vx * vx + vy * vy + vz * vz)
        if speed > cfg.speed_max_mps:
            bad("speed", f"speed {speed:.2f} m/s > {cfg.speed_max_mps:g} m/s")
    return out


def check(inputs: SafetyInputs, fence: Fence, cfg: SafetyConfig, limits: CommandLimits | None = None) -> Decision:
    """The per-tick safety decision (pure: same inputs, same decision)."""
    violations: list[Violation] = []
    if inputs.operator_kill:
        violations.append(Violation("operator_kill", None, STOP_ALL, f"operator kill ({inputs.operator_kill})"))
    if not (inputs.tick_late_s <= cfg.overrun_stop_s):
        violations.append(Violation("loop_overrun", None, STOP_ALL,
                                    f"tick {inputs.tick_late_s * 1e3:.0f} ms late (limit {cfg.overrun_stop_s * 1e3:.0f} ms)"))
    elif inputs.tick_late_s > inputs.dt:
        violations.append(Violation("tick_skipped", None, NONE,
                                    f"tick {inputs.tick_late_s * 1e3:.1f} ms late: "
                                    f"{int(inputs.tick_late_s / inputs.dt)} tick(s) skipped"))
    for i, d in enumerate(inputs.drones):
        violations += check_drone(i, d, inputs.t, inputs.dt, fence, cfg, limits)
    if inputs.operator_land:
        violations.append(Violation("operator_land", None, LAND_ALL, f"operator: land now ({inputs.operator_land})"))
    stop_all = any(v.action == STOP_ALL for v in violations)
    n = len(inputs.drones)
    stop = tuple(stop_all or any(v.drone == i and v.action == STOP_DRONE for v in violations) for i in range(n))
    land_all = any(v.action == LAND_ALL for v in violations)
    land = tuple(not stop[i] and (land_all or any(v.drone == i and v.action == LAND_DRONE for v in violations))
                 for i in range(n))
    return Decision(stop, stop_all, tuple(violations), land)
