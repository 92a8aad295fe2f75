"""The tick's memory for the soft failsafes and the landings (cfrace.flight.loop.tick.TickCore uses it):
mocap glitches and low-battery time per drone, what lies in a drone's way, starting a drone's
landing and running one tick of it. docs/flight.md, "Safety" and "Landing"."""

from __future__ import annotations

import functools
import math

import numpy as np

from cfrace.contract.actions import FIRMWARE_MIN_THRUST_COUNTS, thrust_to_counts
from cfrace.flight.landing import descent as ld
from cfrace.flight.landing import spots
from cfrace.sim.gates import to_gate_frame

OPPONENT_AHEAD_M = 0.5   #: m, a downed drone counts as in the way only this far along the path or more
BRAKE_LAG_S = 0.3        #: s the braking takes to turn the thrust round (flown on at speed meanwhile)
#: s a drone may fly on on its policy before it lands where braking is not safe (brakes_unsafe): after
#: the race's end (land_after_race), and after a DEFERRABLE soft failsafe (may_start_landing)
FLY_THROUGH_MAX_S = 1.0
#: m, a drone this near the line of one that flies on (and ahead of it, within its brake's sep_m) flies
#: on with it (fly_on_together): two radii and a drift; 0.42 m off it, braking lets it pass
FLY_ON_LANE_M = 0.25
#: soft landings that may wait (at most FLY_THROUGH_MAX_S) for a place where braking is safe: the drone
#: flies on on its policy meanwhile. Not those whose cause lies ahead of the drone (a downed drone, the
#: fence) or in its poses.
DEFERRABLE = ("low_battery", "operator_land")
GLITCH_DROPOUT_S = 0.05  #: s, a pose dropout this long counts as a mocap glitch (shorter ones: frame jitter)
GLITCH_WINDOW_S = 2.0    #: s, glitches this recent count
#: landing spots chosen per tick at most (2-8 ms each on a 2-core VM, docs/flight.md "The loop at N drones"):
#: when 8 drones start landing in one tick the choice spreads over 8 ticks instead of making one 21-34 ms long
SPOTS_PER_TICK = 1


def kept_clear_of(drones: list, skip=None) -> tuple[list, list]:
    """What a new landing spot keeps clear of (spots.choose_landing_spots' ``others`` and ``paths``):
    the drones down where they lie and the spots of the landing drones (but ``skip``) that have one,
    and those drones' paths to their spots."""
    landing = [o.landing for o in drones if o is not skip and o.landing is not None and o.landing.spot is not None]
    others = [o.frozen_pos for o in drones if o.stopped and o.frozen_pos is not None] + [lp.spot for lp in landing]
    return others, [(lp.start, lp.spot) for lp in landing if lp.start is not None]


def blocked_by(i: int, drones: list, pos, gate: np.ndarray, clearance: float) -> str:
    """A stopped drone within ``clearance`` of drone i's straight path from ``pos`` to ``gate`` (3,),
    at least OPPONENT_AHEAD_M along it ("" if none)."""
    down = [o for j, o in enumerate(drones) if j != i and o.stopped and o.frozen_pos is not None]
    if not down:     # (asked every tick for every racing drone: while nothing is down, no work)
        return ""
    pos = np.asarray(pos, np.float64)
    if not np.all(np.isfinite(pos)):
        return ""
    seg = np.asarray(gate, np.float64) - pos
    length = max(float(np.linalg.norm(seg)), 1e-9)
    for o in down:
        p = np.asarray(o.frozen_pos, np.float64)
        u = min(1.0, max(0.0, float((p - pos) @ seg) / (length * length)))
        # in the way = near the path AHEAD (not beside the drone: at a ground start both stand there)
        if u * length >= OPPONENT_AHEAD_M and float(np.linalg.norm(pos + u * seg - p)) < clearance:
            return f"{o.name} down at ({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f})"
    return ""


def brakes_out_of_fence(pos, vel, fence, setup: ld.LandingSetup) -> bool:
    """Would braking in a straight line from here (braking_distance) end outside ``fence`` (seen from
    above, the drone's radius inside it)? A racing drone heading for a wall turns before it; one that
    brakes instead may fly through the fence."""
    pos, vel = np.asarray(pos, np.float64), np.asarray(vel, np.float64)
    speed = float(np.linalg.norm(vel[:2]))
    if not (math.isfinite(speed) and np.all(np.isfinite(pos))) or speed < 1e-6:
        return False
    stop = pos[:2] + vel[:2] / speed * braking_distance(float(np.linalg.norm(vel)), setup.brake)
    r = setup.radius
    return not all(fence.lo[k] + r <= stop[k] <= fence.hi[k] - r for k in (0, 1))


def braking_distance(speed: float, brake: ld.BrakeController) -> float:
    """m a drone at ``speed`` m/s flies on while ``brake`` stops it: BRAKE_LAG_S at speed, then the
    deceleration k_vel v, at most accel_max."""
    v_cap = brake.accel_max / brake.k_vel        # below this speed the deceleration is k_vel v
    if speed <= v_cap:
        return speed * BRAKE_LAG_S + speed / brake.k_vel
    return speed * BRAKE_LAG_S + (speed * speed - v_cap * v_cap) / (2.0 * brake.accel_max) + v_cap / brake.k_vel


def brakes_unsafe(pos, vel, gate, fence, setup: ld.LandingSetup) -> bool:
    """Would braking from here take the drone out of ``fence`` (brakes_out_of_fence) or into the frame
    of ``gate``, its target (brakes_into_gate)? The one rule by which a drone told to land flies on
    first: after the race's end (SoftState.land_after_race) and for a DEFERRABLE soft failsafe
    (SoftState.may_start_landing)."""
    return brakes_out_of_fence(pos, vel, fence, setup) or brakes_into_gate(pos, vel, gate, setup)


def brakes_into_gate(pos, vel, gate, setup: ld.LandingSetup) -> bool:
    """Would braking from here take the drone into ``gate`` (x, y, z, yaw)? It flies towards the
    gate's plane from the approach side and some part of the gate's frame lies within its braking
    distance (a braking drone does not fly straight on: one in a turn drifts half a metre sideways
    while it brakes, towards the gate its policy was turning to). It cannot be sure to stop clear of
    the frame then, and only its policy flies it through the opening."""
    pos, vel = np.asarray(pos, np.float64), np.asarray(vel, np.float64)
    local = to_gate_frame(pos, np.asarray(gate, np.float64))
    c, s = math.cos(float(gate[3])), math.sin(float(gate[3]))
    closing = c * vel[0] + s * vel[1]              # velocity along the gate's normal
    if not (np.all(np.isfinite(local)) and math.isfinite(closing) and local[0] > 0.0 and closing < 0.0):
        return False
    reach = braking_distance(float(np.linalg.norm(vel)), setup.brake) + setup.gate_half + setup.radius
    return float(np.linalg.norm(local)) < reach


def fly_on_together(racing: list, fly: set, ests: list, reach: float, lane: float = FLY_ON_LANE_M) -> set:
    """The drones of ``racing`` that fly on after the race's end: those of ``fly`` and, in a chain,
    every one with a valid estimate in the way of one that flies on: less than ``reach`` m ahead of
    it along its velocity and less than ``lane`` m off that line, flying the same way. Braking there,
    it would be run into from behind; a drone behind, beside or off the line of one that flies on, or
    coming towards it, brakes (it falls back, and braking keeps it off the others,
    ld.separation_accel)."""
    fly, grown = set(fly), True
    while grown:
        grown = False
        for i in racing:
            if i in fly or not ests[i].valid:
                continue
            for j in fly:
                gap, v = ests[i].pos - ests[j].pos, ests[j].vel
                speed = float(np.linalg.norm(v))
                along = float(gap @ v) / speed if speed > 1e-6 else -1.0
                if 0.0 < along < reach and float(np.linalg.norm(gap - along * v / speed)) < lane \
                        and float(ests[i].vel @ v) > 0.0:
                    fly.add(i)
                    grown = True
                    break
    return fly


class SoftState:
    """Per drone: when its pose glitched, since when its battery is low, whether it held for another
    drone's landing; log records to flush."""

    def __init__(self, n: int):
        self.glitches = [[] for _ in range(n)]   # times of pose dropouts / outliers
        self.dropping = [False] * n
        self.outliers = [0] * n
        self.rejecting = [False] * n              # the last tick rejected an outlier (an episode runs)
        self.vbat_low_since: list = [None] * n
        self.pending_records: list = []           # log records made outside the tick's _records
        self.holding: set = set()                 # drones that have held for another one's path
        self.spot_queue: list = []                # drones landing without a spot yet, first come first
        self.land_asked: dict = {}                # drone -> t it was first told to land (may_start_landing)
        self.race_on = True                       # until land_after_race: landing spots keep off the race line

    def count_glitches(self, drones: list, ests: list, t: float, counters: dict) -> None:
        """Remember when each drone's pose dropped out for GLITCH_DROPOUT_S, or began to be rejected
        as an outlier: one glitch per episode. Outliers tick after tick are one episode (a pose source
        that jumped, e.g. replayed frames), which the consistency check judges (pose_mismatch), so a
        soft landing does not start on poses that belong to no drone."""
        for i, (d, e) in enumerate(zip(drones, ests)):
            dropping = float(e.age_s) > GLITCH_DROPOUT_S
            if dropping and not self.dropping[i]:
                self.glitches[i].append(t)
            self.dropping[i] = dropping
            c = counters[d.body]["outliers"]
            rejected = c > self.outliers[i]
            if rejected and not self.rejecting[i]:
                self.glitches[i].append(t)
            self.rejecting[i], self.outliers[i] = rejected, c

    def recent_glitches(self, i: int, t: float) -> int:
        return sum(1 for g in self.glitches[i] if t - g <= GLITCH_WINDOW_S)

    def track_battery(self, t: float, links, limit_v: float) -> None:
        """Since when each drone's battery has been below ``limit_v`` without a break."""
        for i, link in enumerate(links):
            if not float(getattr(link, "vbat", math.nan)) < limit_v:
                self.vbat_low_since[i] = None
            elif self.vbat_low_since[i] is None:
                self.vbat_low_since[i] = t

    def low_battery_s(self, i: int, t: float) -> float:
        return 0.0 if self.vbat_low_since[i] is None else t - self.vbat_low_since[i]

    def land_after_race(self, drones: list, ests: list, t: float, t_end: float, targets, fence,
                        setup: ld.LandingSetup) -> None:
        """After the race's end (at t_end) every drone still racing lands, but one whose braking would
        take it into the gate ahead of it or out of ``fence`` (brakes_unsafe) flies on on its policy
        first, for at most FLY_THROUGH_MAX_S after the end: it lands once braking is safe (through one
        gate, it may be too close to the next) or that time is up. A drone
        just ahead of one that flies on, in its way, flies on with it (fly_on_together): braking there,
        it would be run into from behind."""
        self.race_on = False
        racing = [i for i, d in enumerate(drones) if not d.stopped and d.landing is None]
        if not racing:
            return
        fly = set()
        if t - t_end < FLY_THROUGH_MAX_S:
            fly = {i for i in racing if ests[i].valid and brakes_unsafe(ests[i].pos, ests[i].vel,
                                                                       setup.gates[int(targets[i])], fence, setup)}
            fly = fly_on_together(racing, fly, ests, setup.brake.sep_m)
        for i in racing:
            if i not in fly:
                self.start_landing(drones, i, ests[i], t, "race_end", setup)

    def off_line(self, drones: list) -> bool:
        """Must a landing spot keep off the race line? While the race goes on and another drone races
        (flying, not landing) on it."""
        return self.race_on and any(not o.stopped and o.landing is None for o in drones)

    def may_start_landing(self, drones: list, i: int, est, t: float, kinds: list, gate, fence,
                          setup: ld.LandingSetup) -> bool:
        """May drone i, told to land for ``kinds`` at t, start braking now? A landing of the DEFERRABLE
        kinds alone waits while braking would take the drone out of the fence or into the frame of
        ``gate``, its target (brakes_unsafe), for at most FLY_THROUGH_MAX_S from the
        first tick it was told: the drone races on meanwhile (a low battery is no reason to brake into
        a wall; its gates still count). An /event says when it flies on and when it brakes anyway."""
        if not all(k in DEFERRABLE for k in kinds) or not est.valid:
            return self.asked_done(i)
        first = self.land_asked.setdefault(i, t)
        if not brakes_unsafe(est.pos, est.vel, gate, fence, setup):
            return self.asked_done(i)
        d = drones[i]
        if t - first >= FLY_THROUGH_MAX_S or t == first:
            text = (f"{', '.join(kinds)}: flew on for {t - first:.1f} s, brakes anyway" if t > first else
                    f"{', '.join(kinds)}: flies on (braking here would take it out of the fence or into a gate)")
            self.pending_records.append(("/event", {"kind": "landing", "drone": d.name, "body": d.body, "text": text}))
        return self.asked_done(i) if t - first >= FLY_THROUGH_MAX_S else False

    def asked_done(self, i: int) -> bool:
        """Drone i is no longer waiting to land (it lands now, or nothing asks it to): True."""
        self.land_asked.pop(i, None)
        return True

    def start_landing(self, drones: list, i: int, est, t: float, reason: str, setup: ld.LandingSetup) -> None:
        """Drone i stops racing and lands: it brakes at once; its spot (clear of the drones already down
        and of the other landing drones' spots) comes from choose_spots, in the order the drones began
        to land, from where it is expected to stop."""
        d = drones[i]
        stop = ld.stopping_point(est.pos, est.vel, setup.brake.accel_max)
        brake = ld.BrakeController(**{**setup.brake.__dict__, "hold_z": None})
        d.landing = ld.LandingPilot(brake, None, setup.ground_z, setup.cfg, start=np.asarray(stop, np.float64)[:2],
                                    respot=functools.partial(self._respot, drones, i, setup),
                                    may_go=functools.partial(self._may_go, drones, i, setup))
        d.landing_result = {"reason": reason, "t_start": round(t, 4)}
        self.spot_queue.append(i)

    def choose_spots(self, drones: list, setup: ld.LandingSetup, budget: int = SPOTS_PER_TICK) -> None:
        """Landing spots for at most ``budget`` drones of the queue (a drone waiting for its spot
        brakes on, ld.LandingPilot.step). No free spot: straight down where it stops."""
        while self.spot_queue and budget > 0:
            d = drones[self.spot_queue.pop(0)]
            if d.stopped or d.landing is None:
                continue
            budget -= 1
            others, paths = kept_clear_of(drones)
            try:
                spot = spots.choose_landing_spots(setup.track, [d.landing.start], others, setup.cfg, paths,
                                                  off_line=self.off_line(drones))[0]
            except ValueError:
                spot = d.landing.start.copy()
            d.landing.spot = spot
            d.landing_result["spot"] = [round(float(v), 3) for v in spot]
            self.pending_records.append(("/event", {
                "kind": "landing", "drone": d.name, "body": d.body,
                "text": f"{d.landing_result['reason']}: landing at ({spot[0]:.2f}, {spot[1]:.2f})"}))

    def _respot(self, drones: list, i: int, setup: ld.LandingSetup, pos, spot) -> np.ndarray:
        """Drone i's spot once its braking is over: the one chosen if the straight path from where it
        stopped keeps clear of the gates and obstacles (spots.path_clear), else the nearest spot that
        does (the braking ends where it ends, not always where stopping_point expected it)."""
        d, here = drones[i], np.asarray(pos, np.float64)[:2]
        spot = self._swap_with_braking(drones, i, setup, here, np.asarray(spot, np.float64))
        if spots.path_clear(setup.track, here, spot, setup.cfg.path_clearance_m):
            return spot
        others, paths = kept_clear_of(drones, skip=d)
        try:
            new = spots.choose_landing_spots(setup.track, [here], others, setup.cfg, paths, off_line=self.off_line(drones))[0]
        except ValueError:
            return spot
        d.landing.start = here.copy()
        d.landing_result["spot"] = [round(float(v), 3) for v in new]
        self.pending_records.append(("/event", {"kind": "landing", "drone": d.name, "body": d.body,
                                                "text": f"braked at ({here[0]:.2f}, {here[1]:.2f}): landing at "
                                                        f"({new[0]:.2f}, {new[1]:.2f}) instead"}))
        return new

    def _swap_with_braking(self, drones: list, i: int, setup: ld.LandingSetup, here, spot) -> np.ndarray:
        """Drone i, about to fly from ``here`` to ``spot``, swaps spots with a drone still braking when
        that makes their two paths shorter together (spots.swap_pays: then they do not cross) and both
        new paths are clear. Two drones that brake side by side otherwise may fly their go-tos across
        each other from a few centimetres apart. Returns drone i's spot."""
        clear = functools.partial(spots.path_clear, setup.track, clearance=setup.cfg.path_clearance_m)
        for j, o in enumerate(drones):
            lp = o.landing
            if j == i or o.stopped or lp is None or lp.phase not in (ld.BRAKE, ld.HOLD) or lp.pos is None \
                    or lp.spot is None:
                continue
            there = lp.pos[:2]
            if spots.swap_pays(here, spot, there, lp.spot) and clear(here, lp.spot) and clear(there, spot):
                spot, lp.spot = np.asarray(lp.spot, np.float64), spot
                for k, new in ((i, spot), (j, lp.spot)):
                    drones[k].landing_result["spot"] = [round(float(v), 3) for v in new]
                    self.pending_records.append(("/event", {
                        "kind": "landing", "drone": drones[k].name, "body": drones[k].body,
                        "text": f"spots swapped ({drones[i].name}, {o.name}): landing at ({new[0]:.2f}, {new[1]:.2f})"}))
                break
        return spot

    def _may_go(self, drones: list, i: int, setup: ld.LandingSetup, t: float) -> bool:
        """May drone i, braked, start its go-to at loop time t? Not while, flown at the same time as
        planned (LandingPilot.plan), it would come nearer than path_separation_m (or than the two are
        now, if nearer) to a landing drone that goes first: one flying its go-to or landing, or one
        braking or holding at a lower height (its brake's hold height; ties: the lower index). Two
        drones that stop close together otherwise fly their go-tos side by side, or one descends onto
        the other; two that move apart both go."""
        me = drones[i].landing
        key, sep = (me.brake.hold_z or math.inf, i), setup.cfg.path_separation_m
        for j, o in enumerate(drones):
            lp = o.landing
            if j == i or o.stopped or lp is None or lp.phase == ld.DOWN or lp.pos is None:
                continue
            if lp.phase in (ld.BRAKE, ld.HOLD) and (lp.brake.hold_z or math.inf, j) > key:
                continue                                    # it waits for drone i
            if lp.spot is None:
                return False                                # its way is not known yet (choose_spots)
            taus = np.linspace(0.0, max(me.left_s(t), lp.left_s(t), 0.1), 64)
            closest = float(np.min(np.linalg.norm(me.plan(t, taus) - lp.plan(t, taus), axis=1)))
            if closest < min(sep, float(np.linalg.norm(me.pos - lp.pos))) - 1e-6:
                if i not in self.holding:
                    self.holding.add(i)
                    here = me.pos
                    self.pending_records.append(("/event", {
                        "kind": "landing", "drone": drones[i].name, "body": drones[i].body,
                        "text": f"holds at ({here[0]:.2f}, {here[1]:.2f}) until {o.name} is out of its way"}))
                return False
        return True


def flying_others(i: int, drones: list, ests: list) -> list:
    """(pos, vel) of the drones but i still flying (racing or landing, with a valid estimate): what
    drone i's braking keeps away from (ld.separation_accel looks at those within its reach); none
    while drone i's own estimate is not valid (held, not measured)."""
    if not ests[i].valid:
        return []
    return [(e.pos, e.vel) for j, (o, e) in enumerate(zip(drones, ests)) if j != i and not o.stopped and e.valid]


def land_step(i: int, drones: list, ests: list, t: float, out_commands: list, timeout_s: float) -> tuple | None:
    """One tick of landing drone i of drones: its rate setpoint while braking, else None; its
    high-level commands appended to out_commands; when it is down (or its landing timed out) the
    touchdown goes into its landing_result with "down"."""
    d, est = drones[i], ests[i]
    step = d.landing.step(t, est.pos, est.vel, est.quat, flying_others(i, drones, ests))
    for name, args in step.high_level:
        out_commands.append((i, name, args))
    if step.notify_stop:
        out_commands.append((i, "notify_stop", {}))
        if d.landing.held_s > 0.0:
            d.landing_result["held_s"] = round(d.landing.held_s, 3)
    td = d.landing.touchdown
    if step.done or (t - d.landing_result["t_start"] > timeout_s):
        d.landing_result.update(td.as_dict() if td is not None else {})
        d.landing_result["down"] = bool(step.done) and not d.landing.hit_floor
        if d.landing.hit_floor:
            d.landing_result["cut"] = "floor_braking"      # it fell on the floor braking: a crash, not a landing
        return None
    if step.rates_dps is None:
        d.counts, d.thrust_n = 0, 0.0
        return None
    counts = int(np.clip(thrust_to_counts(step.thrust_n, d.thrust_curve), FIRMWARE_MIN_THRUST_COUNTS, 60000))
    d.rates_dps, d.counts, d.thrust_n = tuple(float(r) for r in step.rates_dps), counts, step.thrust_n
    return (*d.rates_dps, counts)
