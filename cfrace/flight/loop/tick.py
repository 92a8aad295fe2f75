"""The tick: (state, newest poses, link figures) -> (setpoints, safety decision, log records).

``TickCore.step`` is everything a tick decides, with no I/O: it reads no clock, no mocap, no link
and writes no log. Its inputs are the tick (index, race time, lateness), the newest mocap frame,
the time the estimator predicts to, each link's figures (LinkInputs) and the operator's kill
request; its state is the race's own (estimator, race progress, the drones' last actions and
stops, which safety violations are active). It returns a TickOut: the setpoint to send to each
drone (or None), the drones to stop now, the safety decision, the new safety events and the log
records of the tick. The runner (cfrace.flight.loop.flight_loop.FlightLoop) owns clock, mocap, links and log.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from cfrace.contract.actions import FIRMWARE_MIN_THRUST_COUNTS
from cfrace.flight.landing import descent as ld
from cfrace.flight.safety import check as sf
from cfrace.flight.mocap.consistency import ConsistencyMonitor
from cfrace.flight.safety.failsafe import SoftState, blocked_by, land_step
from cfrace.flight.loop.swarm import OpponentPicker, batched_step, due_groups
from cfrace.flight.loop.state import FlownDrone, ObservationBuilder
from cfrace.flight.mocap.sources import frame_to_msg

#: thrust counts sent at least while a drone races: the Crazyflie firmware turns a legacy setpoint
#: below 1000 counts (MIN_THRUST, crtp_commander_rpyt.c) into zero thrust, and at zero thrust its
#: controller resets and stops controlling the body rates (motors idle). The training simulator
#: keeps the rate control at zero collective thrust (rotor forces clamped at >= 0), and the
#: policies use it (full rates at zero thrust in sharp turns). 1000 counts is 2-4 % of the weight.
FLYING_MIN_COUNTS = FIRMWARE_MIN_THRUST_COUNTS


class LinkInputs(NamedTuple):
    """What the tick needs of one drone's link (its figures, read by the runner)."""

    connected: bool
    rx_age_s: float       #: s since the last packet from the drone
    vbat: float = math.nan   #: V, the drone's battery as its link reports it (nan: unknown)


class TickIn(NamedTuple):
    k: int
    t: float              #: s, race time
    late_s: float         #: s the tick started after its deadline
    now: float            #: s, the time the estimator predicts the poses to


@dataclass
class TickOut:
    """What one tick decided (TickCore.step)."""

    setpoints: list       #: per drone (p, q, r deg/s, thrust counts) to send, or None
    stops: list           #: (drone index, kind) of the drones to stop now
    decision: sf.Decision
    events: list          #: the safety events new this tick (dicts, as in the result)
    records: list         #: (topic, payload) of the flight log, this tick's
    obs_s: list           #: per drone: s the observation took (nan when it did not infer)
    infer_s: list         #: per drone: s the ONNX run took
    est_map: dict
    ests: list
    end: str = ""         #: "" while the race goes on
    winner: str = "draw"
    commands: list = field(default_factory=list)  #: (drone index, "notify_stop" or a high-level command, args)


class TickCore:
    """The race state and the pure tick over it (module doc)."""

    def __init__(self, *, drones: list[FlownDrone], estimator, progress, obs_builder: ObservationBuilder,
                 fence: sf.Fence, safety_cfg, laps: int, timeout_s: float, dt: float, filters=None,
                 limits: sf.CommandLimits | None = None, landing: ld.LandingSetup | None = None,
                 hover_start: bool = False, consistency: bool = True):
        self.landing = landing   #: None: every stop cuts the motors (no landing)
        self.hover_start = hover_start   #: drones hover (high-level commander) until their first inference
        self.race_over: tuple | None = None   #: (end, winner, t, tally()) once the race is decided
        self.soft = SoftState(len(drones))   #: what the soft failsafes and the landings remember
        self.drones, self.estimator, self.progress = drones, estimator, progress
        self.obs_builder, self.fence, self.safety_cfg = obs_builder, fence, safety_cfg
        self.laps, self.timeout_s, self.dt, self.filters = laps, timeout_s, float(dt), filters
        self.limits = limits   #: what a sent setpoint may hold (None: not checked)
        self.events: list[dict] = []
        self._active: set = set()        # (kind, drone) of violations currently present
        self._outliers = {d.body: 0 for d in drones}
        #: do the poses move with the commands (off only for scripted poses in unit tests)
        self.consistency = ConsistencyMonitor(len(drones), dt, drones[0].mass) if drones and consistency else None
        self.mismatch: list = [None] * len(drones)   #: per drone: why its poses do not fit its commands
        self.t = 0.0
        self.last_ests: list | None = None
        self.last_frame = None
        self.opponents = OpponentPicker(drones, progress)   #: more than two drones: who observes whom

    # ------------------------------------------------------------------ pieces
    def event(self, t: float, v: sf.Violation) -> dict:
        ev = {"t": round(t, 4), "kind": v.kind, "drone": None if v.drone is None else self.drones[v.drone].name,
              "body": None if v.drone is None else self.drones[v.drone].body, "action": v.action, "detail": v.detail}
        self.events.append(ev)
        return ev

    def mark_stopped(self, i: int, t: float, kind: str) -> bool:
        """Drone i stops for good (sticky); True if it was flying until now."""
        d = self.drones[i]
        if d.stopped:
            return False
        d.stopped, d.stop_kind, d.stop_t = True, kind, t
        d.counts, d.thrust_n = 0, 0.0
        return True

    @staticmethod
    def due(d: FlownDrone, k: int) -> bool:
        """Drone d infers on tick k (its policy rate, staggered by its phase); not while it lands."""
        return not d.stopped and d.landing is None and k % d.decimation == d.phase % d.decimation

    def _opponent(self, i: int, ests: list):
        """The estimate drone i observes as its opponent (None: its layout has none)."""
        if len(ests) == 2:
            return ests[1 - i]
        return ests[self.opponents.index(i, ests)] if self.drones[i].layout.opponent else None

    def group_observations(self, group: list[int], ests: list) -> np.ndarray:
        """(M, D): the observations of the drones of ``group`` (drones of one policy, so one layout),
        built in one call (ObservationBuilder.many)."""
        return self.obs_builder.many(self.drones[group[0]].layout, [ests[i] for i in group],
                                     [int(self.progress.target[i]) for i in group],
                                     [self._opponent(i, ests) for i in group])

    def observe_group(self, group: list[int], ests: list) -> np.ndarray:
        """group_observations() through the fault hooks' filter (TickCore.filters), if any."""
        obs = self.group_observations(group, ests)
        if self.filters is not None:
            obs = np.stack([self.filters.filter_obs(self.drones[i], o) for i, o in zip(group, obs)])
        return obs

    def _act(self, i: int, obs: np.ndarray, act: np.ndarray) -> None:
        """Drone i's action (filtered) through its action map into its next setpoint."""
        d = self.drones[i]
        if self.filters is not None:
            act = self.filters.filter_action(d, act, self.t)
        thrust, rates, counts = d.setpoint_map(act)
        d.obs, d.action, d.thrust_n, d.rates_dps = obs, act, thrust, rates
        # FLYING_MIN_COUNTS, not 0: a zero-thrust setpoint makes the firmware reset its rate
        # controller and idle the motors; the policy's zero thrust means "rotors as low as the rate
        # control allows", as in training (docs/flight.md, "Trained policies through the flight stack")
        d.counts = max(FLYING_MIN_COUNTS, counts) if math.isfinite(thrust) else 0

    def positions(self, ests: list) -> list[tuple[float, float, float]]:
        """Per drone, the position for race progress on floats: a stopped drone stays where it
        stopped; non-finite values are 0."""
        out = []
        for d, e in zip(self.drones, ests):
            p = d.frozen_pos if d.stopped and d.frozen_pos is not None else e.pos
            x, y, z = float(p[0]), float(p[1]), float(p[2])
            out.append((x if math.isfinite(x) else 0.0, y if math.isfinite(y) else 0.0, z if math.isfinite(z) else 0.0))
        return out

    def _blocked(self, i: int, ests: list) -> str:
        d = self.drones[i]
        if d.stopped or d.landing is not None or self.landing is None:
            return ""
        return blocked_by(i, self.drones, ests[i].pos, self.landing.gates[int(self.progress.target[i])][:3],
                          self.safety_cfg.opponent_clearance_m)

    def safety_inputs(self, t: float, late_s: float, ests: list, computed: list, hit, links, kill,
                      land: str | None = None) -> sf.SafetyInputs:
        soft = self.landing is not None
        return sf.SafetyInputs(
            t=t, dt=self.dt, tick_late_s=late_s, operator_kill=kill, operator_land=land if soft else None,
            drones=tuple(sf.DroneInputs(
                pos=e.pos, vel=e.vel, rot=e.rot, est_valid=bool(e.valid), est_age_s=float(e.age_s),
                obs=d.obs if computed[i] else None, action=d.action,
                link_connected=links[i].connected, link_rx_age_s=links[i].rx_age_s,
                gate_crash=bool(hit[i]),
                command=None if d.stopped or d.landing is not None else (*d.rates_dps, d.counts),
                landing=d.landing is not None or not soft,
                mocap_glitches=self.soft.recent_glitches(i, t), blocked=self._blocked(i, ests),
                vbat=float(getattr(links[i], "vbat", math.nan)), vbat_low_s=self.soft.low_battery_s(i, t),
                pose_mismatch=self.mismatch[i])
                for i, (d, e) in enumerate(zip(self.drones, ests))))

    # ------------------------------------------------------------------ the tick
    def step(self, tick: TickIn, frame, links: list[LinkInputs], kill: str | None = None,
             land: str | None = None) -> TickOut:
        """One tick on the newest frame (None: no new one); see the module doc."""
        k, t = tick.k, tick.t
        self.t = t
        if frame is not None:
            self.last_frame = frame
        est_map = self.estimator.update(frame, tick.now)
        ests = self.last_ests = [est_map[d.body] for d in self.drones]
        passed, lap_done, hit = self.progress.update(t, self.positions(ests))
        n = len(self.drones)
        infer, obs_t, computed = [np.nan] * n, [np.nan] * n, [False] * n
        for group in due_groups(self.drones, [self.due(d, k) for d in self.drones]):
            times, call_s = batched_step(self, group, ests)
            for i, o in zip(group, times):
                computed[i], obs_t[i], infer[i] = True, o, call_s
        if self.consistency is not None:
            self.mismatch = self.consistency.update_all(self.drones, ests)
        if self.landing is not None:
            self.soft.count_glitches(self.drones, ests, t, self.estimator.counters)
            self.soft.track_battery(t, links, self.safety_cfg.low_battery_v)
        decision = sf.check(self.safety_inputs(t, tick.late_s, ests, computed, hit, links, kill, land),
                            self.fence, self.safety_cfg, self.limits)
        if self.landing is not None and not decision.stop_all:
            for i, d in enumerate(self.drones):
                if not (decision.land[i] and not d.stopped and d.landing is None):
                    self.soft.asked_done(i)       # (a drone that flew on, then was no longer told to land)
                    continue
                kinds = [v.kind for v in decision.violations if v.action in (sf.LAND_DRONE, sf.LAND_ALL)
                         and v.drone in (i, None)]
                gate = self.landing.gates[int(self.progress.target[i])]
                if self.soft.may_start_landing(self.drones, i, ests[i], t, kinds, gate, self.fence, self.landing):
                    self.soft.start_landing(self.drones, i, ests[i], t, kinds[0], self.landing)
            self.soft.choose_spots(self.drones, self.landing)   # this tick's and earlier ones' landings
        commands: list = []
        setpoints, stops = self._setpoints(decision, ests, t, k, commands)
        end, winner = self._end(decision, ests, t)
        out = TickOut(setpoints, stops, decision, [], [], obs_t, infer, est_map, ests, end, winner, commands)
        self._events(out, t, k)
        self._records(out, t, k, frame, computed, passed.any() or lap_done.any())
        return out

    def _end(self, decision, ests: list, t: float) -> tuple[str, str]:
        """(end, winner) of this tick. With landing: once the race is decided every drone still flying
        lands (SoftState.land_after_race: on its policy first while braking would take it into its
        target gate's frame or out of the fence), and the loop ends when every drone is down or
        stopped (a hard stop ends it at once)."""
        end, winner = self.race_end(decision, t)
        if self.landing is None or decision.stop_all:
            return end, winner
        if self.race_over is None and end:
            self.race_over = (end, winner, t, self.tally())
        if self.race_over is not None:
            self.soft.land_after_race(self.drones, ests, t, self.race_over[2], self.progress.target, self.fence,
                                     self.landing)
        if any(not d.stopped and (d.landing is not None or self.race_over is not None) for d in self.drones):
            return "", "draw"
        return (self.race_over[0], self.race_over[1]) if self.race_over is not None else (end, winner)

    def _setpoints(self, decision, ests: list, t: float, k: int, commands: list) -> tuple[list, list]:
        setpoints, stops = [None] * len(self.drones), []
        for i, d in enumerate(self.drones):
            if d.landing is not None and not d.stopped and not decision.stop[i]:
                setpoints[i] = land_step(i, self.drones, ests, t, commands, self.landing.timeout_s)
                if d.landing_result is not None and "down" in d.landing_result:
                    d.frozen_pos = ests[i].pos.copy()
                    d.stop_k = k
                    kind = "landed" if d.landing_result["down"] else d.landing_result.get("cut", "landing_timeout")
                    if self.mark_stopped(i, t, kind):
                        stops.append((i, kind))
                continue
            if decision.stop[i]:
                kinds = [v.kind for v in decision.violations
                         if v.action != sf.NONE and (v.drone == i or v.drone is None)]
                if not d.stopped:
                    d.frozen_pos = ests[i].pos.copy()
                    d.stop_k = k
                kind = kinds[0] if kinds else "safety"
                if d.landing_result is not None and "down" not in d.landing_result and not d.stopped:
                    d.landing_result.update(d.landing.touchdown.as_dict() if d.landing.touchdown else {})
                    d.landing_result.update(down=False, cut=kind)
                if self.mark_stopped(i, t, kind):
                    stops.append((i, kind))
            elif not d.stopped:
                if self.hover_start and d.action is None:
                    continue   # hovering on the high-level commander until its first inference
                r = d.rates_dps
                setpoints[i] = (r[0], r[1], r[2], d.counts)
        for d, sp in zip(self.drones, setpoints):   # the command the estimator's latency compensation flies on
            self.estimator.command(d.body, d.thrust_n / d.mass if sp and d.landing is None and not d.stopped else None)
        return setpoints, stops

    def _events(self, out: TickOut, t: float, k: int) -> None:
        """Each violation once per episode (it re-arms when it clears), pose outliers, speeds."""
        present = set()
        for v in out.decision.violations:
            key = (v.kind, v.drone)
            present.add(key)
            if v.drone is not None and self.drones[v.drone].stopped and self.drones[v.drone].stop_k != k:
                continue   # a stopped drone's later state (falling, on the floor) is no news
            if key not in self._active:
                out.events.append(self.event(t, v))
        self._active = present
        counters = self.estimator.counters
        for i, d in enumerate(self.drones):
            c = counters[d.body]["outliers"]
            if c > self._outliers[d.body]:
                self._outliers[d.body] = c
                out.events.append(self.event(t, sf.Violation(
                    "pose_outlier", i, sf.NONE, f"mocap pose of {d.body} rejected as an outlier ({c} so far)")))
            e = out.ests[i]
            if not d.stopped and d.landing is None and e.valid:   # racing: the speeds of the race alone
                vx, vy, vz = e.vel.tolist()
                s = math.sqrt(vx * vx + vy * vy + vz * vz)
                d.speed_max = max(d.speed_max, s)
                d.speed_sum += s
                d.speed_n += 1

    def _records(self, out: TickOut, t: float, k: int, frame, computed: list, progressed: bool) -> None:
        """This tick's flight log records (topics: docs/flight-log.md); /timing and /link are the runner's."""
        rec = out.records
        rec += self.soft.pending_records
        self.soft.pending_records = []
        for ev in out.events:
            rec.append(("/safety", {key: ev[key] for key in ("kind", "drone", "body", "action", "detail")}))
        for i, kind in out.stops:
            d = self.drones[i]
            rec.append(("/event", {"kind": "stop", "drone": d.name, "body": d.body, "text": f"stopped: {kind}"}))
            if d.landing_result is not None:
                rec.append(("/landing", {"drone": d.name, "body": d.body, "end": kind, **d.landing_result}))
        for i, name, args in out.commands:
            d = self.drones[i]
            rec.append(("/event", {"kind": "high_level", "drone": d.name, "body": d.body,
                                   "text": f"{name} {args}" if args else name}))
        if frame is not None:
            rec.append(("/mocap/pose", {**frame_to_msg(frame), "k": k}))
        rec.append(("/estimate", {b: {"pos": e.pos, "vel": e.vel, "quat": e.quat, "age_s": e.age_s,
                                      "valid": e.valid} for b, e in out.est_map.items()}))
        if any(computed):
            done = [d for c, d in zip(computed, self.drones) if c]
            rec.append(("/obs", {"k": k, **{d.body: d.obs for d in done}}))
            rec.append(("/action", {"k": k, **{d.body: d.action for d in done}}))
        rec.append(("/setpoint", {d.body: {"stopped": d.stopped, "thrust_n": d.thrust_n, "thrust_counts": d.counts,
                                           "rates_dps": np.array(d.rates_dps)} for d in self.drones}))
        if progressed:
            rec.append(("/race", self.race_state()))

    def race_end(self, decision, t: float) -> tuple[str, str]:
        """(end, winner) after this tick; end "" while the race goes on."""
        if decision.stop_all:   # includes the operator kill (a signal seen by this tick's check)
            return next(v.kind for v in decision.violations if v.action == sf.STOP_ALL), "draw"
        n = len(self.drones)
        done = [i for i in range(n) if self.progress.laps[i] >= self.laps and not self.drones[i].stopped]
        if done:
            return "finished", (self.drones[done[0]].name if len(done) == 1 else "draw")
        if all(d.stopped for d in self.drones):
            return "all_stopped", "draw"
        if t >= self.timeout_s:
            return "timeout", "draw"
        return "", "draw"

    # ------------------------------------------------------------------ warm-up (outputs discarded)
    def peek(self, k: int, now: float, links: list[LinkInputs]) -> None:
        """What tick k will compute, on copies of the state and the newest frame, outputs
        discarded: the observation, policy and action map of every drone due on it and the safety
        check (the clock's warm-up, cfrace.flight.loop.clock). Raises what the tick would raise."""
        ests = self.last_ests
        if ests is not None:
            est_map = self.estimator.peek(self.last_frame, now)
            ests = [est_map[d.body] for d in self.drones]
            self.progress.peek(self.positions(ests))
        for group in due_groups(self.drones, [self.due(d, k) for d in self.drones]):   # as step() runs them
            lead = self.drones[group[0]]
            obs = self.group_observations(group, ests) if ests is not None else \
                np.zeros((len(group), lead.layout.dim), np.float32)
            for i, a in zip(group, np.asarray(lead.policy(obs), dtype=np.float32).reshape(len(group), 4)):
                self.drones[i].setpoint_map(a)
        if ests is not None:
            n = len(ests)
            sf.check(self.safety_inputs(self.t, 0.0, ests, [True] * n, [False] * n, links, None),
                     self.fence, self.safety_cfg, self.limits)

    def warm_policies(self, calls: int) -> None:
        """Every drone's policy and action map ``calls`` times on a zero observation, outputs discarded."""
        for d in self.drones:
            obs = np.zeros((1, d.layout.dim), np.float32)
            for _ in range(calls):
                d.setpoint_map(np.asarray(d.policy(obs), dtype=np.float32).reshape(4))

    # ------------------------------------------------------------------ results
    def tally(self) -> list[tuple[int, int, list]]:
        """Per drone (gates passed, laps, lap times): as at the race's end once it is decided (a drone
        flying on through the gate ahead before it lands scores nothing more), else as now."""
        if self.race_over is not None:
            return self.race_over[3]
        p = self.progress
        return [(int(p.gates_passed[i]), int(p.laps[i]), list(p.lap_times[i])) for i in range(len(self.drones))]

    def race_state(self) -> dict:
        return {d.body: {"drone": d.name, "gates_passed": g, "laps": laps, "target": int(self.progress.target[i]),
                         "lap_times": list(lt), "stopped": d.stopped, "stop_kind": d.stop_kind}
                for i, (d, (g, laps, lt)) in enumerate(zip(self.drones, self.tally()))}

    def drone_results(self) -> list[dict]:
        out = []
        for i, (d, (g, laps, lt)) in enumerate(zip(self.drones, self.tally())):
            out.append({"name": d.name, "body": d.body, "policy": str(d.meta.get("path", "")),
                        "method": d.meta.get("method"), "laps": laps, "gates_passed": g,
                        "lap_times": [round(x, 3) for x in lt], "stopped": d.stopped,
                        "stop_kind": d.stop_kind, "stop_t": None if d.stop_t != d.stop_t else round(d.stop_t, 3),
                        "landing": d.landing_result,
                        "speed_max": round(d.speed_max, 3),
                        "pose_residual_max": None if self.consistency is None else
                        {"rate_dps": round(self.consistency.worst[i][0], 1),
                         "dv_of_limit": round(self.consistency.worst[i][1], 3)},
                        "speed_mean": round(d.speed_sum / d.speed_n, 3) if d.speed_n else None})
        return out
