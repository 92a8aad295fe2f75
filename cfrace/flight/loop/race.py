"""Fly one race: the thin runner around the flight loop. It owns the clock, the links, the mocap
source and the log it gets from a RaceIO (cfrace.flight.setup) and stops every drone on every way out.

Order (nothing is sent to a drone before every check passed):
  1. track, drone profile, both policies loaded and checked (cfrace.flight.setup.resolve_race,
     done by the caller: PolicyError / ConfigError);
  2. the mocap source opened and every body seen (MocapError: unknown body);
  3. every link connected (LinkError: no answer / no Crazyradio / nothing listening), then the
     poses watched for RaceIO.still_s: they must not move while nothing is armed (MocapError:
     the pose source does not belong to these drones; cfrace.flight.mocap.consistency);
  4. every link set up (rate mode params, arming, zero-thrust unlock), then the loop.
Every exit after step 2 (race end, exception, Ctrl-C, SIGTERM, safety) goes through one finally
block that stops every drone, closes the links and the mocap source and closes the log with a
/summary. SIGINT/SIGTERM during the race ask the loop to stop everything on its next tick
(<= 10 ms); before the race (connecting, setting up) a signal raises KeyboardInterrupt at once
(the finally still stops every drone); once the loop has ended, signals are only recorded
(``operator_kill``, the exit code): nothing interrupts the stop sequence and the log's close.
A flight log that cannot be written refuses the race before the set-up (its path and the Foxglove
port are checked at the CLI edge, before anything opens); a write error during the
flight is the result's ``log_error`` (and the exit code's, EXIT_CODES["log_error"]).
"""

from __future__ import annotations

import gc
import signal
import sys
import threading
import time
from dataclasses import asdict
from typing import Callable


from cfrace.errors import LogError
from cfrace.flight.loop import realtime
from cfrace.flight.safety import check as sf
from cfrace.flight.mocap.consistency import check_still
from cfrace.flight.link.opener import check_link, wait_heard
from cfrace.flight.loop.swarm import check_take_off
from cfrace.flight.mocap.estimation import PREDICTION, PoseEstimator
from cfrace.flight.log.foxglove_scene import log_write_error, open_sink
from cfrace.flight.landing.descent import LandingSetup
from cfrace.flight.log.timing import loop_figures
from cfrace.flight.loop.flight_loop import FlownDrone, FlightLoop, KillSwitch, LoopResult, ObservationBuilder
from cfrace.flight.loop.state import RaceResult, inference_phases
from cfrace.flight.landing.procedures import hover_start, hover_start_positions
from cfrace.flight.loop.gate_progress import FastRaceProgress
from cfrace.flight.setup import RaceIO, RaceSetup, real_io

#: exit codes of `fly` / `sim dry-run` besides 0 (docs/flight.md, "Exit codes"); 74: EX_IOERR
EXIT_CODES = {"SIGINT": 130, "SIGTERM": 143, "log_error": 74, "all_stopped": 3, "error": 1}


def result_exit_code(result: dict, late_signal: str | None = None) -> int:
    """A race's exit code from its JSON, the one rule of `fly` and `sim dry-run`: 143 / 130 when the
    operator's signal ended or followed the race (also while its result was written: late_signal);
    74 when the flight log could not be written; 1 when the race raised; 0 when it ran to an end
    someone could win (finished, time-out); else 3: the safety checks stopped every drone."""
    signal_name = result.get("operator_kill") or late_signal
    end = result.get("end")
    if signal_name or end == "operator_kill":
        return EXIT_CODES.get(signal_name or "", 130)
    if result.get("log_error"):
        return EXIT_CODES["log_error"]
    if end == "error":
        return EXIT_CODES["error"]
    if end in ("finished", "timeout"):
        return 0
    return EXIT_CODES["all_stopped"]     # all_stopped, or a check that stopped every drone at once


def timing_summary(timing: dict, dt: float, names: list[str]) -> dict:
    """p50 / p99 / max in ms of the loop's per-tick figures (cfrace.flight.log.timing: the same
    function `cfrace log info` uses)."""
    return loop_figures(timing, dt, names)


def _run_realtime_friendly(loop: FlightLoop, rt_priority: int = 0, loop_cpu: int | None = None
                           ) -> tuple[LoopResult, bool, int | None]:
    """Run the loop with Python tuned for a steady 100 Hz: everything allocated so far is frozen
    out of the garbage collector (no long full collections mid-race) and the automatic collection is
    off for the race (the loop collects after each tick's send instead: cfrace.flight.loop.flight_loop.collect_garbage,
    so that no collection lands inside a tick), the GIL switch interval
    drops from 5 ms to 0.5 ms (a woken loop thread waits at most that for cflib's threads), the
    loop thread gets ``loop_cpu`` to itself (every other thread of the process goes to the other
    CPUs; cfrace.flight.loop.realtime) and with rt_priority > 0 it runs SCHED_FIFO where permitted (it
    sleeps most of each period, so it cannot starve the machine). Returns (result, whether SCHED_FIFO
    was in effect, the loop's CPU if it was pinned)."""
    gc.collect()
    gc.freeze()
    gc_was_on = gc.isenabled()
    gc.disable()
    old_switch = sys.getswitchinterval()
    sys.setswitchinterval(0.0005)
    old_sched = realtime.set_fifo(rt_priority)
    old_cpus = None
    try:
        old_cpus = realtime.pin_loop_thread(loop_cpu)
        return loop.run(), old_sched is not None, loop_cpu if old_cpus is not None else None
    finally:
        realtime.restore_affinity(old_cpus)
        realtime.restore_scheduler(old_sched)
        sys.setswitchinterval(old_switch)
        if gc_was_on:
            gc.enable()
        gc.unfreeze()


class _Signals:
    """SIGINT/SIGTERM -> the operator kill. Before the loop runs (``may_raise()`` true) it also
    raises KeyboardInterrupt; while the loop runs the loop stops every drone on its next tick;
    after it, nothing is interrupted (the stop sequence and the log's close run to their end)."""

    def __init__(self, kill: KillSwitch, may_raise: Callable[[], bool]):
        self.kill, self.may_raise, self.old = kill, may_raise, {}

    def _handler(self, signum, frame):
        name = signal.Signals(signum).name
        self.kill.request(name)
        if self.may_raise():
            raise KeyboardInterrupt(name)

    def _land_handler(self, signum, frame):
        self.kill.request_land(signal.Signals(signum).name)

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                self.old[s] = signal.signal(s, self._handler)
            self.old[signal.SIGUSR1] = signal.signal(signal.SIGUSR1, self._land_handler)   # "land now"
        return self

    def __exit__(self, *exc):
        for s, h in self.old.items():
            signal.signal(s, h)


class SignalGuard:
    """SIGINT/SIGTERM around a whole command (`cfrace fly`, `cfrace sim dry-run`): before and during
    the race a signal interrupts (the race's own handling takes over while it runs); once ``after``
    is set (the race is over, its result is being printed and written) a signal is only recorded in
    ``late``, so the JSON and the exit code still come out, and from the guard's end to the exit
    signals are ignored."""

    def __init__(self):
        self.late: str | None = None
        self.after = False
        self.old: dict = {}

    def _handler(self, signum, frame):
        name = signal.Signals(signum).name
        self.late = self.late or name
        if not self.after:
            raise KeyboardInterrupt(name)

    def _unraisable(self, u) -> None:
        """A signal's KeyboardInterrupt raised where it cannot propagate (a weakref or finalizer
        callback during the race's teardown) is already in ``late``; anything else is printed."""
        if isinstance(u.exc_value, KeyboardInterrupt) and self.late is not None:
            return
        self.old_unraisable(u)

    def __enter__(self) -> "SignalGuard":
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                self.old[s] = signal.signal(s, self._handler)
            self.old_unraisable, sys.unraisablehook = sys.unraisablehook, self._unraisable
        return self

    def __exit__(self, *exc) -> None:
        for s, h in self.old.items():   # after the race the command only exits: signals are ignored
            signal.signal(s, signal.SIG_IGN if self.after else h)


def _quietly(call: Callable[[], object]) -> None:
    """Call, ignoring any exception (clean-up on the way out: every step must run)."""
    try:
        call()
    except Exception:  # noqa: BLE001
        pass


class RaceRun:
    """One race from a resolved set-up and its I/O: open, fly, always stop and close."""

    def __init__(self, setup: RaceSetup, io: RaceIO, *, extra_meta=None, settle=None, console=None, announce=None):
        self.setup, self.io = setup, io
        self.settle, self.console, self.announce = settle, console, announce
        cfg = setup.cfg
        # ConfigError before anything flies; a lockstep clock is neither pinned nor SCHED_FIFO
        real_time = io.clock.realtime
        self.loop_cpu = realtime.resolve_loop_cpu(cfg.loop_cpu) if real_time else None
        rt_priority = realtime.resolve_rt_priority(cfg.rt_priority) if real_time else 0
        self.kill = KillSwitch()
        self.phase = "open"    #: open (before the loop), fly, shut_down
        self.links, self.mocap, self.log, self.view = [], None, None, None
        self.result = RaceResult()
        self.meta = {"track": setup.track.name, "obstacles": cfg.obstacles, "laps": cfg.laps,
                     "profile": setup.profile.name, "rate_hz": cfg.rate_hz, "bodies": list(cfg.bodies),
                     "uris": list(io.uris), "mocap": cfg.mocap, "lockstep": not real_time,
                     "safety": asdict(cfg.safety), "velocity_alpha": cfg.velocity_alpha,
                     "latency_comp_s": cfg.latency_comp, "latency_prediction": PREDICTION, "loop_cpu": self.loop_cpu, "rt_priority": rt_priority,
                     "timeout_s": cfg.timeout_s, "landing": cfg.landing, "start": cfg.start,
                     "policies": {n: {"path": str(p.path), **p.policy.meta}
                                  for n, p in zip(cfg.names, setup.policies)},
                     **({"notes": list(setup.notes)} if setup.notes else {}),
                     **(extra_meta or {})}

    def run(self) -> RaceResult:
        with _Signals(self.kill, lambda: self.phase == "open"):
            try:
                loop = self._open()
                self.phase = "fly"
                self._fly(loop)
            except BaseException as exc:
                self.result.error = f"{type(exc).__name__}: {exc}"
                if self.kill.reason is not None:
                    self.result.operator_kill = self.kill.reason
                raise
            finally:
                self.phase = "shut_down"
                self._shut_down()
            if self.kill.reason is not None:
                self.result.operator_kill = self.kill.reason
        return self.result

    def _open(self) -> FlightLoop:
        """Steps 2-4 of the module doc, then the loop, ready to run."""
        cfg, io = self.setup.cfg, self.io
        self.mocap = io.open_mocap()
        self.mocap.open(cfg.mocap_timeout_s)
        self._check_separation()
        for i, uri in enumerate(io.uris):
            self.links.append(check_link(io.open_link(i, uri), uri))
        for link in self.links:
            link.connect(cfg.connect_timeout_s)
        if io.still_s > 0:     # before anything is armed: the poses must not move on their own
            check_still(self.mocap, list(cfg.bodies), io.still_s)
        # the flight log and/or the live Foxglove server (cfrace.flight.log.foxglove_scene)
        self.log = open_sink(cfg.log, self.meta, self.setup.track, self.setup.fence, list(cfg.bodies), cfg.obstacles,
                             cfg.foxglove_port, scene=cfg.foxglove_scene)
        server = getattr(self.log, "server", None)
        if (error := log_write_error(self.log)) is not None:    # e.g. a full disk: its first write failed
            raise LogError(f"cannot write flight log {cfg.log}: {error.strerror or error}")
        if self.announce is not None:
            self.announce(self.meta | {"fence": self.setup.fence, "foxglove": server.url if server else None})
        for link in self.links:
            link.setup()
        if io.still_s > 0:    # real links: every drone answered just now, or the race does not start
            wait_heard(self.links, self.io.link_clock, self.setup.cfg.safety.link_timeout_s / 2.0)
        return self._loop()

    def _check_separation(self) -> None:
        """The take-off rules (swarm.check_take_off: separation, start grid); nothing was sent yet."""
        self.mocap = check_take_off(self.mocap, self.setup.cfg, self.io.clock.realtime, self.setup.track)

    def _drones(self) -> list[FlownDrone]:
        s = self.setup
        return [FlownDrone(name=name, body=s.cfg.bodies[i], policy=p.policy, layout=p.layout,
                      link=self.links[i], meta=dict(p.policy.meta, path=str(p.path)), mass=s.profile.mass,
                      thrust_curve=s.profile.thrust_curve, decimation=p.decimation, phase=phase)
                for i, (name, p, phase) in enumerate(zip(s.cfg.names, s.policies, inference_phases(s.policies)))]

    def _loop(self) -> FlightLoop:
        s, cfg, io = self.setup, self.setup.cfg, self.io
        drones = self._drones()
        estimator = PoseEstimator(list(cfg.bodies), stale_after_s=cfg.safety.mocap_stale_s,
                                  alpha=cfg.velocity_alpha, lead_s=cfg.latency_comp)
        if not cfg.quiet:
            from cfrace.flight.log.liveview import LiveView
            self.view = LiveView(title=f"cfrace {s.track.name}: " + " vs ".join(d.meta["method"] for d in drones),
                                 laps=cfg.laps,
                                 every_ticks=int(round(cfg.rate_hz / cfg.view_hz)), console=self.console)
            self.view.__enter__()
        loop = FlightLoop(drones=drones, mocap=self.mocap, estimator=estimator,
                          progress=FastRaceProgress(s.track.gate_array(), len(drones)),
                          obs_builder=ObservationBuilder(s.track.gate_corners()), clock=io.clock, fence=s.fence,
                          safety_cfg=cfg.safety, laps=cfg.laps, timeout_s=cfg.timeout_s, log=self.log,
                          view=self.view, faults=io.hooks, kill=self.kill, link_clock=io.link_clock,
                          prewarm_s=io.prewarm_s, limits=s.limits,
                          landing=LandingSetup.for_race(s.track, s.profile) if cfg.landing else None,
                          hover_start=cfg.start == "hover", pose_stream=cfg.pose_stream)
        return loop

    def _hover_start(self) -> dict:
        """--start hover: every drone takes off to its start position on the high-level commander
        (cfrace.flight.landing.procedures.hover_start) before the race's clock starts."""
        s = self.setup
        targets, yaw = hover_start_positions(s.track, len(self.links))
        latest: dict = {}

        def poses() -> dict:
            frame = self.mocap.read(0.0)
            if frame is not None:
                latest.update({b: (p.pos, p.quat) for b, p in frame.poses.items()})
            return latest
        poses()
        wait = self.io.wait or time.sleep
        report = hover_start(self.links, list(s.cfg.bodies), poses, wait, targets, yaw)
        wait(s.cfg.dt)   # one more period: the race's first tick then reads a frame of its own
        if self.log is not None:
            self.log.write("/event", 0.0, {"kind": "hover_start", "text": f"hovering at the start: {report}"})
        return report

    def _fly(self, loop: FlightLoop) -> None:
        s, log = self.setup, self.log
        hover = self._hover_start() if s.cfg.start == "hover" else None
        if log is not None:
            log.write("/event", 0.0, {"kind": "start", "text": "race start"})
        res, fifo, loop_cpu = _run_realtime_friendly(loop, self.meta["rt_priority"], self.loop_cpu)
        self.result = RaceResult(
            end=res.end, winner=res.winner, duration_s=round(res.t_end, 3), operator_kill=self.kill.reason,
            rt_fifo=fifo, loop_cpu=loop_cpu, track=s.track.name, profile=s.profile.name,
            loop=timing_summary(res.timing, s.cfg.dt, [d.name for d in loop.drones])
            | {"skipped": res.skipped, "poses_sent": loop.poses_sent,
               "setpoints_sent": sum(d.link.quality.sent for d in loop.drones)},
            safety_events=res.safety_events, drones=res.drones,
            estimator={b: dict(c) for b, c in loop.estimator.counters.items()},
            laps={d["name"]: d["laps"] for d in res.drones}, lap_times={d["name"]: d["lap_times"] for d in res.drones},
            hover_start=hover, landings={d["name"]: d.get("landing") for d in res.drones})
        ests = loop.core.last_ests if hasattr(loop, "core") else None
        if ests is not None:   # landing: who was too close when every drone was stopped
            close = sf.too_close({d.body: e.pos for d, e in zip(loop.drones, ests) if e.valid},
                                 s.cfg.safety.min_separation_m)
            self.result.separation_at_stop = [{"bodies": [a, b], "distance_m": d} for a, b, d in close]
        if log is not None:
            log.write("/race", res.t_end, {"final": True, **loop.race_state(), "end": res.end, "winner": res.winner})

    def _shut_down(self) -> None:
        """Every way out: stop every drone first, then settle, close links, mocap, log."""
        result = self.result
        for link in self.links:
            _quietly(link.stop)
        if self.view is not None:
            self.view.__exit__(None, None, None)
        if self.settle is not None:
            try:
                result.drones_final = self.settle()
            except Exception as exc:  # noqa: BLE001
                result.drones_final_error = str(exc)
        for link in self.links:
            _quietly(link.close)
        if self.mocap is not None:
            _quietly(self.mocap.close)
        if self.io.hooks is not None and hasattr(self.io.hooks, "log"):
            result.faults = self.io.hooks.log
        if self.log is not None:
            doc = result.to_json()
            self.log.close({k: v for k, v in doc.items() if k != "loop"} | {"loop": doc.get("loop")})
            if self.setup.cfg.log is not None:
                result.log = str(self.setup.cfg.log)
            if (error := log_write_error(self.log)) is not None:
                result.log_error = f"{self.setup.cfg.log}: {error.strerror or error}"


def run_race(setup: RaceSetup, io: RaceIO, *, extra_meta=None, settle=None, console=None,
             announce=None) -> RaceResult:
    """Fly one race and return its RaceResult (docs/flight.md). settle(): called after every drone
    was stopped, returns what the result and the log summary store as drones_final (the dry-run
    waits for motors off there); announce(meta): called once every check passed and every link
    answered, before the set-up."""
    return RaceRun(setup, io, extra_meta=extra_meta, settle=settle, console=console, announce=announce).run()


def fly(setup: RaceSetup, console=None, announce=None) -> RaceResult:
    """`cfrace fly`: real drones (radio:// or udp://) from a mocap system."""
    return run_race(setup, real_io(setup.cfg), console=console, announce=announce)
