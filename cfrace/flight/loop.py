"""The 100 Hz flight loop: mocap -> estimate -> race progress -> observation -> ONNX -> action map
-> safety -> link, every tick, for every drone; logging and the live view after the send.

Rates: setpoints are streamed to every drone on every tick (100 Hz) and the safety check runs
every tick, so a stop reaches a drone within one period and a lost radio packet is replaced
10 ms later; the policies run at their metadata ``policy_hz`` (50 Hz: inference on every 2nd
tick), as in training where one action holds for 20 ms; between inferences the last command is
re-sent. The drones' inferences are staggered (ego on even ticks, opponent on odd ticks): each
still acts at 50 Hz on a fresh observation, and no tick carries two inferences, which halves the
worst per-tick compute.

What one tick measures (all in /timing): ``late_s`` (start against its absolute deadline),
``period_s`` (start to start), ``compute_s`` (start to the last setpoint handed to the links: the
latency the loop adds), ``compute_cpu_s`` (the CPU time the loop thread spent on it: the same
without the time other processes took the CPU), and per drone ``obs_s`` (the observation) and
``infer_s`` (the ONNX run).

Warm-up window (``prewarm_s`` > 0, real time; 3 ms by default): code run after a sleep is slow
on this machine (the paper-size actor: ~0.4 ms every 10 ms with sleeps in between against ~0.09
ms back to back; benchmarks/onnx_cold.py). So from ``prewarm_s`` before each deadline the clock
calls ``prewarm`` over and over (RealClock.wait_next): the tick's pure parts on the newest data
(estimator and race progress on copies of their state, the observation, policy and action map of
the drone due on that tick, the safety check), outputs discarded; then, once, each link's send
path (``warm_links``, Link.warm: for udp:// links a zero setpoint through cflib's UDP driver to a
socket of our own, nothing to the drone); then it waits the rest without sleeping. The tick
itself then computes on fresh data as before (tests/test_flight_core_run.py: a race with and
without it is bit-identical). The warm-up costs
CPU time in the idle part of the period, not latency; its CPU time and passes per tick are
recorded (``prewarm_s``, ``prewarm_calls`` in /timing).

Pings: when the race starts the links stop their own ping timers (Link.pace_pings) and the loop
pings every drone every 100 ms right after its setpoints, so that the answers are handled in the
idle part of the period, not in the middle of a tick.
"""

from __future__ import annotations

import math
import time

import numpy as np

from cfrace.env.actions import FIRMWARE_MIN_THRUST_COUNTS
from cfrace.flight import safety as sf
from cfrace.flight.loopstate import Drone, KillSwitch, LoopResult, ObservationBuilder, TickTimes
from cfrace.flight.mocap import frame_to_msg

__all__ = ["FlightLoop", "Drone", "KillSwitch", "LoopResult", "ObservationBuilder", "FLYING_MIN_COUNTS"]

#: thrust counts sent at least while a drone races: the Crazyflie firmware turns a legacy setpoint
#: below 1000 counts (MIN_THRUST, crtp_commander_rpyt.c) into zero thrust, and at zero thrust its
#: controller resets and stops controlling the body rates (motors idle). The training simulator
#: keeps the rate control at zero collective thrust (rotor forces clamped at >= 0), and the
#: policies use it (full rates at zero thrust in sharp turns). 1000 counts is 2-4 % of the weight.
FLYING_MIN_COUNTS = FIRMWARE_MIN_THRUST_COUNTS

PRE_RACE_WARM_CALLS = 20   #: policy calls per drone before the clock starts (FlightLoop.warm_policies)

perf = time.perf_counter
thread_time = time.thread_time   # CPU time of this thread: the tick's own cost, without preemption


class FlightLoop:
    """Runs one race. Construct with ready (connected, set up) links and an opened mocap source."""

    def __init__(self, *, drones: list[Drone], mocap, estimator, progress, obs_builder: ObservationBuilder,
                 clock, fence: sf.Fence, safety_cfg, laps: int, timeout_s: float, log=None, view=None,
                 faults=None, kill: KillSwitch | None = None, link_log_every: int = 10, link_clock=None,
                 prewarm_s: float = 0.0):
        self.drones, self.mocap, self.estimator, self.progress = drones, mocap, estimator, progress
        self.obs_builder, self.clock, self.fence, self.safety_cfg = obs_builder, clock, fence, safety_cfg
        self.laps, self.timeout_s, self.log, self.view, self.faults = laps, timeout_s, log, view, faults
        self.kill = kill or KillSwitch()
        self.link_log_every = link_log_every
        self.ping_every = max(1, round(0.1 / clock.dt))   #: ticks between pings (100 ms, as cflib's own)
        self.link_clock = link_clock or time.monotonic   #: the clock the links stamp last_rx with
        self.events: list[dict] = []
        self._active: set = set()        # (kind, drone) of violations currently present
        self._outliers = {d.body: 0 for d in drones}
        self.running = False
        self.t = 0.0
        self._now = 0.0
        self.prewarm_s = float(prewarm_s)
        self._last_ests: list | None = None
        self._last_frame = None
        self._warm_s, self._warm_n = float("nan"), 0

    # ------------------------------------------------------------------ helpers
    def _event(self, t: float, v: sf.Violation) -> None:
        ev = {"t": round(t, 4), "kind": v.kind, "drone": None if v.drone is None else self.drones[v.drone].name,
              "body": None if v.drone is None else self.drones[v.drone].body, "action": v.action, "detail": v.detail}
        self.events.append(ev)
        if self.log is not None:
            self.log.write("/safety", t, {k: ev[k] for k in ("kind", "drone", "body", "action", "detail")})

    def _stop(self, i: int, t: float, kind: str) -> None:
        d = self.drones[i]
        if d.stopped:
            return
        d.stopped, d.stop_kind, d.stop_t = True, kind, t
        d.link.stop()
        d.counts, d.thrust_n = 0, 0.0
        if self.log is not None:
            self.log.write("/event", t, {"kind": "stop", "drone": d.name, "body": d.body, "text": f"stopped: {kind}"})

    def stop_all(self, t: float, kind: str) -> None:
        for i in range(len(self.drones)):
            self._stop(i, t, kind)

    @staticmethod
    def _due(d: Drone, k: int) -> bool:
        """Drone d infers on tick k (its policy rate, staggered by its phase)."""
        return not d.stopped and k % d.decimation == d.phase % d.decimation

    def _observation(self, i: int, ests: list) -> np.ndarray:
        opp = ests[1 - i] if len(ests) == 2 else None
        return self.obs_builder(self.drones[i].layout, ests[i], int(self.progress.target[i]), opp)

    def _policy_step(self, i: int, ests: list, k: int) -> tuple[float, float]:
        """Observation + inference + action map for drone i; returns (observation s, ONNX s)."""
        d = self.drones[i]
        t0 = perf()
        obs = self._observation(i, ests)
        if self.faults is not None:
            obs = self.faults.filter_obs(d, obs)
        t1 = perf()
        act = np.asarray(d.policy(obs[None]), dtype=np.float32).reshape(4)
        t2 = perf()
        if self.faults is not None:
            act = self.faults.filter_action(d, act, self.t)
        thrust, rates, counts = d.setpoint_map(act)
        d.obs, d.action = obs, act
        d.thrust_n = thrust
        d.rates_dps = rates
        # FLYING_MIN_COUNTS, not 0: a zero-thrust setpoint makes the firmware reset its rate
        # controller and idle the motors; the policy's zero thrust means "rotors as low as the rate
        # control allows", as in training (docs/flight.md, "What the dry-run shows ...")
        d.counts = max(FLYING_MIN_COUNTS, counts) if math.isfinite(thrust) else 0
        return t1 - t0, t2 - t1

    def prewarm(self) -> None:
        """Run, outputs discarded, what the next tick will run on fresh data: the observation, policy
        and action map of every drone due to infer on it and the safety check, on the newest
        estimates (see the module doc). The clock calls it repeatedly until just before the
        deadline. Never raises: the tick's own call reports any error."""
        t0 = perf()
        k = self.clock.next_k
        try:
            ests = self._last_ests
            if ests is not None:
                est_map = self.estimator.peek(self._last_frame, self.clock.now())
                ests = [est_map[d.body] for d in self.drones]
                self.progress.peek(self._positions(ests))
            for i, d in enumerate(self.drones):
                if not self._due(d, k):
                    continue
                obs = self._observation(i, ests) if ests is not None else np.zeros(d.layout.dim, np.float32)
                d.setpoint_map(np.asarray(d.policy(obs[None]), dtype=np.float32).reshape(4))
            if ests is not None:
                sf.check(self._safety_inputs(self.t, 0.0, ests, [True] * len(ests), [False] * len(ests)),
                         self.fence, self.safety_cfg)
        except Exception:  # noqa: BLE001 - the tick's real call raises it where it is handled
            pass
        self._warm_s += perf() - t0
        self._warm_n += 1

    def warm_links(self) -> None:
        """Once per tick after the warm-up passes, just before the deadline: every flying drone's
        link exercises its send path without sending to the drone (Link.warm). Never raises."""
        for d in self.drones:
            if not d.stopped:
                try:
                    d.link.warm()
                except Exception:  # noqa: BLE001 - the tick's real send reports link errors
                    pass

    def warm_policies(self, calls: int = PRE_RACE_WARM_CALLS) -> None:
        """Before the race: run every drone's policy and action map ``calls`` times on a zero
        observation, outputs discarded (pure: nothing the race computes changes). Without it the
        first inference of each drone runs cold (about 1 ms for the paper-size actor here, against
        0.08 ms warm): ticks 0 and 1 have no warm-up window before them."""
        for d in self.drones:
            obs = np.zeros((1, d.layout.dim), np.float32)
            for _ in range(calls):
                d.setpoint_map(np.asarray(d.policy(obs), dtype=np.float32).reshape(4))

    def _positions(self, ests: list) -> list[tuple[float, float, float]]:
        """Per drone, the position for race progress on floats: a stopped drone stays where it
        stopped; non-finite values are 0."""
        out = []
        for d, e in zip(self.drones, ests):
            p = d.frozen_pos if d.stopped and d.frozen_pos is not None else e.pos
            x, y, z = float(p[0]), float(p[1]), float(p[2])
            out.append((x if math.isfinite(x) else 0.0, y if math.isfinite(y) else 0.0, z if math.isfinite(z) else 0.0))
        return out

    def _safety_inputs(self, t: float, late_s: float, ests: list, computed: list, hit) -> sf.SafetyInputs:
        return sf.SafetyInputs(
            t=t, dt=self.clock.dt, tick_late_s=late_s, operator_kill=self.kill.reason,
            drones=tuple(sf.DroneInputs(
                pos=e.pos, vel=e.vel, rot=e.rot, est_valid=bool(e.valid), est_age_s=float(e.age_s),
                obs=d.obs if computed[i] else None, action=d.action,
                link_connected=d.link.quality.connected,
                link_rx_age_s=d.link.quality.rx_age(self.link_clock()),
                gate_crash=bool(hit[i])) for i, (d, e) in enumerate(zip(self.drones, ests))))

    # ------------------------------------------------------------------ the loop
    def run(self) -> LoopResult:
        times = TickTimes(len(self.drones))
        end, winner = "", "draw"
        try:
            for d in self.drones:     # before the clock starts: it may wait for cflib's ping thread
                d.link.pace_pings()   # pinged by this loop from now on, after the setpoints (Link.ping)
            if self.prewarm_s > 0.0:  # the first ticks have no warm-up window before them: warm now
                self.warm_policies()
            self.clock.start()
            self.running = True
            while not end:
                end, winner = self._tick(times)
        finally:
            self.running = False
            self.stop_all(self.t, end or "exception")
        return LoopResult(end=end, winner=winner, t_end=self.t, ticks=len(times.compute), skipped=self.clock.skipped,
                          timing=times.arrays(), safety_events=self.events, drones=self.drone_results())

    def _tick(self, times: "TickTimes") -> tuple[str, str]:
        """One tick: wait for it, read the newest poses, estimate, race progress, the due drones'
        policies, the safety check, the setpoints; then the bookkeeping. Returns (end, winner),
        end "" while the race goes on."""
        self._warm_s, self._warm_n = 0.0, 0
        tick = (self.clock.wait_next() if self.prewarm_s <= 0.0
                else self.clock.wait_next(self.prewarm, self.prewarm_s, self.warm_links))
        t_start = perf()
        cpu_start = thread_time()
        k, t = tick.k, tick.t
        self.t = t
        if self.faults is not None:
            self.faults.before_tick(self, t)
        frame = self.mocap.read(0.0)
        if frame is not None:
            self._last_frame = frame
        now = self._now = self.clock.now()
        est_map = self.estimator.update(frame, now)
        ests = self._last_ests = [est_map[d.body] for d in self.drones]
        passed, lap_done, hit = self.progress.update(t, self._positions(ests))
        n = len(self.drones)
        infer, obs_t, computed = [np.nan] * n, [np.nan] * n, [False] * n
        for i, d in enumerate(self.drones):
            if self._due(d, k):
                obs_t[i], infer[i] = self._policy_step(i, ests, k)
                computed[i] = True
        decision = sf.check(self._safety_inputs(t, tick.late_s, ests, computed, hit), self.fence, self.safety_cfg)
        self._send_or_stop(decision, ests, t, k)
        t_sent = perf()
        cpu = thread_time() - cpu_start
        # ---------------------------------------------- after the send: bookkeeping
        times.add(tick, t_sent - t_start, cpu, self._warm_s, self._warm_n, infer, obs_t)
        self._bookkeeping(t, k, tick, frame, est_map, ests, decision, passed, lap_done, t_sent - t_start, cpu,
                          (obs_t, infer), computed)
        return self._race_end(decision, t)

    def _send_or_stop(self, decision, ests: list, t: float, k: int) -> None:
        """Each drone's setpoint to its link, or its stop when the safety decision says so."""
        for i, d in enumerate(self.drones):
            if decision.stop[i]:
                kinds = [v.kind for v in decision.violations
                         if v.action != sf.NONE and (v.drone == i or v.drone is None)]
                if not d.stopped:
                    d.frozen_pos = ests[i].pos.copy()
                    d.stop_k = k
                self._stop(i, t, kinds[0] if kinds else "safety")
            elif not d.stopped:
                r = d.rates_dps
                d.link.send(r[0], r[1], r[2], d.counts)

    def _race_end(self, decision, t: float) -> tuple[str, str]:
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

    def _bookkeeping(self, t, k, tick, frame, est_map, ests, decision, passed, lap_done, compute, cpu, infer,
                     computed) -> None:
        obs_t, infer = infer
        if k % self.ping_every == 0:     # right after the setpoints: answers arrive in the idle part
            for d in self.drones:
                if not d.stopped:
                    d.link.ping()
        # safety: log each violation once per episode (it re-arms when it clears)
        present = set()
        for v in decision.violations:
            key = (v.kind, v.drone)
            present.add(key)
            if v.drone is not None and self.drones[v.drone].stopped and self.drones[v.drone].stop_k != k:
                continue   # a stopped drone's later state (falling, on the floor) is no news
            if key not in self._active:
                self._event(t, v)
        self._active = present
        counters = self.estimator.counters
        for i, d in enumerate(self.drones):
            c = counters[d.body]["outliers"]
            if c > self._outliers[d.body]:
                self._outliers[d.body] = c
                self._event(t, sf.Violation("pose_outlier", i, sf.NONE,
                                            f"mocap pose of {d.body} rejected as an outlier ({c} so far)"))
            e = ests[i]
            if not d.stopped and e.valid:
                s = float(np.linalg.norm(e.vel))
                d.speed_max = max(d.speed_max, s)
                d.speed_sum += s
                d.speed_n += 1
        if self.log is not None:
            self._log_tick(t, k, tick, frame, est_map, passed, lap_done, compute, cpu, obs_t, infer, computed)
        if self.view is not None:
            try:
                self.view.maybe_update(self, t, ests)
            except Exception as exc:  # noqa: BLE001 - a broken terminal must not end the race
                self.view = None
                if self.log is not None:
                    self.log.write("/event", t, {"kind": "view_off", "text": f"live view disabled: {exc}"})

    def _log_tick(self, t, k, tick, frame, est_map, passed, lap_done, compute, cpu, obs_t, infer, computed) -> None:
        """This tick's records in the flight log (topics: docs/flight-log.md)."""
        log = self.log
        if frame is not None:
            log.write("/mocap/pose", t, {**frame_to_msg(frame), "k": k})
        log.write("/estimate", t, {b: {"pos": e.pos, "vel": e.vel, "quat": e.quat, "age_s": e.age_s,
                                       "valid": e.valid} for b, e in est_map.items()})
        if any(computed):
            done = [d for c, d in zip(computed, self.drones) if c]
            log.write("/obs", t, {"k": k, **{d.body: d.obs for d in done}})
            log.write("/action", t, {"k": k, **{d.body: d.action for d in done}})
        log.write("/setpoint", t, {d.body: {"stopped": d.stopped, "thrust_n": d.thrust_n,
                                            "thrust_counts": d.counts, "rates_dps": np.array(d.rates_dps)}
                                   for d in self.drones})
        log.write("/timing", t, {"k": k, "now": self._now,
                                 "late_s": tick.late_s, "skipped": tick.skipped, "compute_s": compute,
                                 "compute_cpu_s": cpu,
                                 "prewarm_s": self._warm_s if self._warm_n else float("nan"), "prewarm_calls": self._warm_n,
                                 "obs_s": {d.body: obs_t[i] for i, d in enumerate(self.drones)},
                                 "infer_s": {d.body: infer[i] for i, d in enumerate(self.drones)}})
        if passed.any() or lap_done.any():
            log.write("/race", t, self.race_state())
        if k % self.link_log_every == 0:
            mono = self.link_clock()
            log.write("/link", t, {d.body: d.link.quality.as_dict(mono) for d in self.drones})

    def race_state(self) -> dict:
        p = self.progress
        return {d.body: {"drone": d.name, "gates_passed": int(p.gates_passed[i]), "laps": int(p.laps[i]),
                         "target": int(p.target[i]), "lap_times": list(p.lap_times[i]), "stopped": d.stopped,
                         "stop_kind": d.stop_kind} for i, d in enumerate(self.drones)}

    def drone_results(self) -> list[dict]:
        p = self.progress
        out = []
        for i, d in enumerate(self.drones):
            out.append({"name": d.name, "body": d.body, "uri": d.link.uri, "policy": str(d.meta.get("path", "")),
                        "method": d.meta.get("method"), "laps": int(p.laps[i]), "gates_passed": int(p.gates_passed[i]),
                        "lap_times": [round(x, 3) for x in p.lap_times[i]], "stopped": d.stopped,
                        "stop_kind": d.stop_kind, "stop_t": None if d.stop_t != d.stop_t else round(d.stop_t, 3),
                        "speed_max": round(d.speed_max, 3),
                        "speed_mean": round(d.speed_sum / d.speed_n, 3) if d.speed_n else None,
                        "link": d.link.quality.as_dict(self.link_clock())})
        return out
