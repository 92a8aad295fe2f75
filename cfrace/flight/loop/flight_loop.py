"""The 100 Hz flight loop: the runner around the tick. Every tick it waits for the clock, reads
the newest mocap frame, calls the pure tick (cfrace.flight.loop.tick.TickCore.step: estimate -> race
progress -> observation -> ONNX -> action map -> safety), hands its setpoints and stops to the
links, and after the send writes the tick's log records and updates the live view.

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
ms back to back; studies/flight_timing/onnx_cold.py). So from ``prewarm_s`` before each deadline the clock
calls ``prewarm`` over and over (RealClock.wait_next): the tick's pure parts on the newest data
(TickCore.peek: estimator and race progress on copies of their state, the observation, policy and
action map of the drone due on that tick, the safety check), outputs discarded; then it waits the
rest without sleeping. The tick itself then computes on fresh data as before
(tests/test_flight_core_run.py: a race with and without it is bit-identical). The warm-up costs
CPU time in the idle part of the period, not latency; its CPU time and passes per tick are
recorded (``prewarm_s``, ``prewarm_calls`` in /timing). It is the one warm-up the loop keeps:
`benchmarks/loop_commits_ab.py` measures compute p99 without it at about 3x its value with it.
The links need none: a setpoint is one write to the link keeper's pipe (cfrace.flight.link.keeper),
whose cflib threads and pings run in their own process.
"""

from __future__ import annotations

import gc
import time

import numpy as np

from cfrace.flight.safety import check as sf
from cfrace.flight.loop.state import FlownDrone, KillSwitch, LoopResult, ObservationBuilder, TickTimes
from cfrace.flight.loop.tick import FLYING_MIN_COUNTS, LinkInputs, TickCore, TickIn

__all__ = ["FlightLoop", "FlownDrone", "KillSwitch", "LoopResult", "ObservationBuilder", "FLYING_MIN_COUNTS"]

PRE_RACE_WARM_CALLS = 20   #: policy calls per drone before the clock starts (FlightLoop.warm_policies)

perf = time.perf_counter
thread_time = time.thread_time   # CPU time of this thread: the tick's own cost, without preemption


def collect_garbage() -> None:
    """The garbage collection of a race, after a tick's send and bookkeeping (outside its compute
    time): the generations Python's automatic collection would collect now, by its own thresholds.
    The runner turns the automatic collection off for the race (runner._run_realtime_friendly), so
    that none lands inside a tick, where a young collection would sit in the tail that makes the
    compute p99 (docs/benchmarks.md, "Garbage collection")."""
    count, limit = gc.get_count(), gc.get_threshold()
    if count[0] < limit[0]:
        return
    gc.collect(2 if count[1] >= limit[1] and count[2] >= limit[2] else 1 if count[1] >= limit[1] else 0)


class FlightLoop:
    """Runs one race. Construct with ready (connected, set up) links and an opened mocap source."""

    def __init__(self, *, drones: list[FlownDrone], mocap, estimator, progress, obs_builder: ObservationBuilder,
                 clock, fence: sf.Fence, safety_cfg, laps: int, timeout_s: float, log=None, view=None,
                 faults=None, kill: KillSwitch | None = None, link_log_every: int = 10, link_clock=None,
                 prewarm_s: float = 0.0, limits: sf.CommandLimits | None = None, landing=None,
                 hover_start: bool = False, pose_stream: bool = False, consistency: bool = True):
        self.core = TickCore(drones=drones, estimator=estimator, progress=progress, obs_builder=obs_builder,
                             fence=fence, safety_cfg=safety_cfg, laps=laps, timeout_s=timeout_s, dt=clock.dt,
                             filters=faults, limits=limits, landing=landing, hover_start=hover_start,
                             consistency=consistency)
        self.pose_stream = bool(pose_stream)   #: send each drone its mocap pose (external position) every frame
        self.poses_sent = 0                    #: poses sent to the drones (all drones together)
        self.mocap, self.clock, self.log, self.view, self.faults = mocap, clock, log, view, faults
        self.kill = kill or KillSwitch()
        self.link_log_every = link_log_every
        self.link_clock = link_clock or time.monotonic   #: the clock the links stamp last_rx with
        self.running = False
        self.prewarm_s = float(prewarm_s)
        self._now = 0.0
        self._warm_s, self._warm_n = float("nan"), 0

    # the race state lives in the tick's core
    drones = property(lambda self: self.core.drones)
    estimator = property(lambda self: self.core.estimator)
    progress = property(lambda self: self.core.progress)
    obs_builder = property(lambda self: self.core.obs_builder)
    events = property(lambda self: self.core.events)
    t = property(lambda self: self.core.t)
    _last_ests = property(lambda self: self.core.last_ests)

    @property
    def fence(self) -> sf.Fence:
        return self.core.fence

    @fence.setter
    def fence(self, fence: sf.Fence) -> None:
        self.core.fence = fence

    def race_state(self) -> dict:
        return self.core.race_state()

    # ------------------------------------------------------------------ I/O around the tick
    def _links(self) -> list[LinkInputs]:
        now = self.link_clock()
        return [LinkInputs(d.link.quality.connected, d.link.quality.rx_age(now), d.link.quality.vbat)
                for d in self.drones]

    def _stop(self, i: int, t: float, kind: str) -> None:
        if self.core.mark_stopped(i, t, kind):
            d = self.drones[i]
            d.link.stop()
            if self.log is not None:
                self.log.write("/event", t, {"kind": "stop", "drone": d.name, "body": d.body, "text": f"stopped: {kind}"})

    def stop_all(self, t: float, kind: str) -> None:
        for i in range(len(self.drones)):
            self._stop(i, t, kind)

    def prewarm(self) -> None:
        """The clock's warm-up pass (TickCore.peek on the next tick). Never raises: the tick's own
        call reports any error."""
        t0 = perf()
        try:
            self.core.peek(self.clock.next_k, self.clock.now(), self._links())
        except Exception:  # noqa: BLE001 - the tick's real call raises it where it is handled
            pass
        self._warm_s += perf() - t0
        self._warm_n += 1

    def warm_policies(self, calls: int = PRE_RACE_WARM_CALLS) -> None:
        """Before the race: run every drone's policy and action map ``calls`` times on a zero
        observation, outputs discarded (pure: nothing the race computes changes). Without it the
        first inference of each drone runs cold (about 1 ms for the paper-size actor here, against
        0.08 ms warm): ticks 0 and 1 have no warm-up window before them."""
        self.core.warm_policies(calls)

    # ------------------------------------------------------------------ the loop
    def run(self) -> LoopResult:
        times = TickTimes(len(self.drones))
        end, winner = "", "draw"
        try:
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

    def _tick(self, times: TickTimes) -> tuple[str, str]:
        """One tick: wait for it, read the newest poses, the pure tick, the setpoints and stops to
        the links; then the bookkeeping. Returns (end, winner), end "" while the race goes on."""
        self._warm_s, self._warm_n = 0.0, 0
        tick = (self.clock.wait_next() if self.prewarm_s <= 0.0
                else self.clock.wait_next(self.prewarm, self.prewarm_s))
        t_start = perf()
        cpu_start = thread_time()
        if self.faults is not None:
            self.core.t = tick.t
            self.faults.before_tick(self, tick.t)
        frame = self.mocap.read(0.0)
        now = self._now = self.clock.now()
        out = self.core.step(TickIn(tick.k, tick.t, tick.late_s, now), frame, self._links(), self.kill.reason,
                             self.kill.land)
        for i, _ in out.stops:
            self.drones[i].link.stop()
        for d, sp in zip(self.drones, out.setpoints):
            if sp is not None:
                d.link.send(*sp)
        for i, name, args in out.commands:      # high-level commands first, then the hand-over
            link = self.drones[i].link
            link.notify_stop() if name == "notify_stop" else link.high_level(name, **args)
        if self.pose_stream and frame is not None:
            for d in self.drones:
                pose = frame.poses.get(d.body)
                if pose is not None and not d.stopped:
                    d.link.send_pose(pose.pos, pose.quat)
                    self.poses_sent += 1
        t_sent = perf()
        cpu = thread_time() - cpu_start
        # ---------------------------------------------- after the send: bookkeeping
        times.add(tick, t_sent - t_start, cpu, self._warm_s, self._warm_n, out.infer_s, out.obs_s)
        if self.log is not None:
            self._log_tick(tick, out, t_sent - t_start, cpu)
        if self.view is not None:
            try:
                self.view.maybe_update(self, tick.t, out.ests)
            except Exception as exc:  # noqa: BLE001 - a broken terminal must not end the race
                self.view = None
                if self.log is not None:
                    self.log.write("/event", tick.t, {"kind": "view_off", "text": f"live view disabled: {exc}"})
        collect_garbage()
        return out.end, out.winner

    def _log_tick(self, tick, out, compute: float, cpu: float) -> None:
        """The tick's records, then the runner's own: /timing, and /link every link_log_every ticks."""
        log, t, k = self.log, tick.t, tick.k
        for topic, payload in out.records:
            log.write(topic, t, payload)
        log.write("/timing", t, {"k": k, "now": self._now,
                                 "late_s": tick.late_s, "skipped": tick.skipped, "compute_s": compute,
                                 "compute_cpu_s": cpu,
                                 "prewarm_s": self._warm_s if self._warm_n else float("nan"), "prewarm_calls": self._warm_n,
                                 "obs_s": {d.body: out.obs_s[i] for i, d in enumerate(self.drones)},
                                 "infer_s": {d.body: out.infer_s[i] for i, d in enumerate(self.drones)}})
        if k % self.link_log_every == 0:
            mono = self.link_clock()
            log.write("/link", t, {d.body: d.link.quality.as_dict(mono) for d in self.drones})

    def drone_results(self) -> list[dict]:
        mono = self.link_clock()
        return [{"name": r["name"], "body": r["body"], "uri": d.link.uri, **r, "link": d.link.quality.as_dict(mono)}
                for r, d in zip(self.core.drone_results(), self.drones)]
