"""`cfrace fly` orchestration: check everything, connect, race, and stop every drone on every way out.

Order (nothing is sent to a drone before every check passed):
  1. track, drone profile, both policies loaded and checked against track, obstacles, layout and
     loop rate (PolicyError / ConfigError);
  2. the mocap source opened and every body seen (MocapError: unknown body);
  3. every link connected (LinkError: no answer / no Crazyradio / nothing listening);
  4. every link set up (rate mode params, arming, zero-thrust unlock), then the loop.
Every exit after step 3 (race end, exception, Ctrl-C, SIGTERM, safety) goes through one finally
block that stops every drone, closes the links and the mocap source and closes the log with a
/summary. SIGINT/SIGTERM during the race ask the loop to stop everything on its next tick
(<= 10 ms); a second signal raises KeyboardInterrupt at once (the finally still stops them).
"""

from __future__ import annotations

import gc
import signal
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from cfrace.drone import load_profile
from cfrace.env.observations import LAYOUTS
from cfrace.errors import PolicyError
from cfrace.flight import realtime
from cfrace.flight.clock import LockstepClock, RealClock
from cfrace.flight.config import DRONE_NAMES, FlightConfig
from cfrace.flight.estimator import PoseEstimator
from cfrace.flight.links import open_link
from cfrace.flight.loop import Drone, FlightLoop, KillSwitch, LoopResult, ObservationBuilder
from cfrace.flight.mocap import open_mocap
from cfrace.flight.progress import FastRaceProgress
from cfrace.flight.safety import Fence
from cfrace.track import load_track

EXIT_CODES = {"SIGINT": 130, "SIGTERM": 143}


def load_checked_policies(cfg: FlightConfig, track) -> list:
    """Both policies, loaded and checked BEFORE anything flies. Returns [(policy, path)]."""
    from cfrace.policy import OnnxPolicy, resolve_policy

    out = []
    for name, spec in zip(DRONE_NAMES, (cfg.ego, cfg.opp)):
        path = resolve_policy(spec, track.name, cfg.obstacles)
        pol = OnnxPolicy(path)
        pol.check(track.name, cfg.obstacles)
        meta = pol.meta
        layout = LAYOUTS[meta["obs_layout"]]
        dec = cfg.rate_hz / meta["policy_hz"]
        if abs(dec - round(dec)) > 1e-6 or round(dec) < 1:
            raise PolicyError(f"{path}: policy_hz {meta['policy_hz']:g} does not divide the {cfg.rate_hz:g} Hz loop")
        if layout.world_position != cfg.obstacles:
            raise PolicyError(f"{path}: layout {layout.name} does not fit a race "
                              f"{'with' if cfg.obstacles else 'without'} obstacles")
        out.append((pol, Path(path)))
    return out


def ms_stats(x) -> dict:
    """p50 / p99 / max in ms of the finite values of x (s); None where there are none."""
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"p50": None, "p99": None, "max": None}
    return {"p50": round(float(np.percentile(x, 50)) * 1e3, 4), "p99": round(float(np.percentile(x, 99)) * 1e3, 4),
            "max": round(float(x.max()) * 1e3, 4)}


def timing_summary(timing: dict, dt: float, names: list[str]) -> dict:
    """p50 / p99 / max in ms of the loop's per-tick figures."""
    stats = ms_stats
    period = np.asarray(timing["period"])
    jitter = np.abs(period - dt)
    out = {"rate_hz": round(1.0 / dt, 3), "ticks": int(len(timing["compute"])),
           "late_ms": stats(timing["late"]), "period_jitter_ms": stats(jitter),
           "compute_ms": stats(timing["compute"]), "compute_cpu_ms": stats(timing.get("compute_cpu", [])),
           "prewarm_ms": stats(timing.get("prewarm", [])),
           "prewarm_calls_mean": (round(float(np.mean(timing["prewarm_calls"])), 2)
                                  if len(timing.get("prewarm_calls", [])) else None),
           "inference_ms": {n: stats(x) for n, x in zip(names, timing["infer"])},
           "observation_ms": {n: stats(x) for n, x in zip(names, timing.get("obs", [[]] * len(names)))}}
    out["period_jitter_p99_ms"] = out["period_jitter_ms"]["p99"]
    out["compute_p99_ms"] = out["compute_ms"]["p99"]
    out["inference_p99_ms"] = max((v["p99"] or 0.0) for v in out["inference_ms"].values())
    return out


def _run_realtime_friendly(loop: FlightLoop, rt_priority: int = 0, loop_cpu: int | None = None
                           ) -> tuple[LoopResult, bool, int | None]:
    """Run the loop with Python tuned for a steady 100 Hz: everything allocated so far is frozen
    out of the garbage collector (no long full collections mid-race), the GIL switch interval
    drops from 5 ms to 0.5 ms (a woken loop thread waits at most that for cflib's threads), the
    loop thread gets ``loop_cpu`` to itself (every other thread of the process goes to the other
    CPUs; cfrace.flight.realtime) and with rt_priority > 0 it runs SCHED_FIFO where permitted (it
    sleeps most of each period, so it cannot starve the machine). Returns (result, whether SCHED_FIFO
    was in effect, the loop's CPU if it was pinned)."""
    gc.collect()
    gc.freeze()
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
        gc.unfreeze()


class _Signals:
    """SIGINT/SIGTERM -> operator kill while the loop runs; KeyboardInterrupt otherwise or on a repeat."""

    def __init__(self, kill: KillSwitch, loop_ref: list):
        self.kill, self.loop_ref, self.old = kill, loop_ref, {}

    def _handler(self, signum, frame):
        name = signal.Signals(signum).name
        loop = self.loop_ref[0] if self.loop_ref else None
        if loop is not None and loop.running and self.kill.reason is None:
            self.kill.request(name)
            return
        self.kill.request(name)
        raise KeyboardInterrupt(name)

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                self.old[s] = signal.signal(s, self._handler)
        return self

    def __exit__(self, *exc):
        for s, h in self.old.items():
            signal.signal(s, h)


def run_race(cfg: FlightConfig, *, fleet=None, lockstep: bool = False, injector=None, mocap_options=None,
             uris=None, extra_meta=None, settle=None, console=None, announce=None,
             lockstep_warm_calls: int = 0) -> dict:
    """Fly one race (real drones or simulated ones) and return the result dict (see docs/flight.md).

    fleet: the in-process SimFleet for `sim` mocap / sim:// links; lockstep: drive it tick by tick
    (with lockstep_warm_calls > 0 the loop's warm-up runs that often before every tick, as it does
    in real time: tests show it changes nothing).
    injector: a faults.FaultInjector; settle(): called after every drone was stopped, returns a
    dict stored in the result and the log summary (the dry-run waits for motors off there).
    announce(meta): called once every check passed and every link answered, before the set-up."""
    from cfrace.flight.flightlog import FlightLog

    track = load_track(cfg.track)
    profile = load_profile(cfg.profile)
    policies = load_checked_policies(cfg, track)
    uris = list(uris or cfg.uris)
    if len(uris) != len(DRONE_NAMES):
        from cfrace.errors import ConfigError
        raise ConfigError(f"--uris: need {len(DRONE_NAMES)} link URIs (ego, opp), got {uris}")
    dt = cfg.dt
    loop_cpu = None if lockstep else realtime.resolve_loop_cpu(cfg.loop_cpu)   # ConfigError before anything flies
    kill = KillSwitch()
    loop_ref: list = []
    links, mocap, log, view = [], None, None, None
    result: dict = {"end": "error", "winner": "draw"}
    clock = LockstepClock(dt, advance=fleet.advance, warm_calls=lockstep_warm_calls) if lockstep else RealClock(dt)
    link_clock = clock.now if lockstep else time.monotonic
    meta = {"track": track.name, "obstacles": cfg.obstacles, "laps": cfg.laps, "profile": profile.name,
            "rate_hz": cfg.rate_hz, "bodies": list(cfg.bodies), "uris": uris, "mocap": cfg.mocap,
            "lockstep": lockstep, "safety": asdict(cfg.safety), "velocity_alpha": cfg.velocity_alpha,
            "latency_comp_s": cfg.latency_comp, "loop_cpu": loop_cpu,
            "rt_priority": 0 if lockstep else realtime.resolve_rt_priority(cfg.rt_priority),
            "policies": {n: {"path": str(p), **pol.meta} for n, (pol, p) in zip(DRONE_NAMES, policies)},
            **(extra_meta or {})}
    with _Signals(kill, loop_ref):
        try:
            mocap = open_mocap(cfg.mocap, bodies=list(cfg.bodies), sim=fleet, **(mocap_options or {}))
            if injector is not None:
                mocap = injector.wrap_mocap(mocap)
            mocap.open(cfg.mocap_timeout_s)
            for uri in uris:
                links.append(open_link(uri, fleet=fleet, clock=link_clock))
            for link in links:
                link.connect(cfg.connect_timeout_s)
            if cfg.log is not None:
                log = FlightLog(cfg.log, meta)
            if announce is not None:
                announce(meta | {"fence": Fence.from_track(track, cfg.safety.geofence_margin_m)})
            for link in links:
                link.setup()
            drones = []
            for i, (name, (pol, path)) in enumerate(zip(DRONE_NAMES, policies)):
                m = dict(pol.meta, path=str(path))
                drones.append(Drone(name=name, body=cfg.bodies[i], policy=pol, layout=LAYOUTS[m["obs_layout"]],
                                    link=links[i], meta=m, mass=profile.mass, thrust_curve=profile.thrust_curve,
                                    decimation=int(round(cfg.rate_hz / m["policy_hz"])), phase=i))
            if injector is not None:
                for d in drones:
                    injector.cutters.setdefault(d.name, getattr(d.link, "cut_link", None))
            estimator = PoseEstimator(list(cfg.bodies), stale_after_s=cfg.safety.mocap_stale_s,
                                      alpha=cfg.velocity_alpha, lead_s=cfg.latency_comp)
            progress = FastRaceProgress(track.gate_array(), len(drones))
            if not cfg.quiet:
                from cfrace.flight.liveview import LiveView
                view = LiveView(title=f"cfrace {track.name}: {drones[0].meta['method']} vs {drones[1].meta['method']}",
                                laps=cfg.laps, every_ticks=int(round(cfg.rate_hz / cfg.view_hz)), console=console)
                view.__enter__()
            loop = FlightLoop(drones=drones, mocap=mocap, estimator=estimator, progress=progress,
                              obs_builder=ObservationBuilder(track.gate_corners()), clock=clock,
                              fence=Fence.from_track(track, cfg.safety.geofence_margin_m), safety_cfg=cfg.safety,
                              laps=cfg.laps, timeout_s=cfg.timeout_s, log=log, view=view, faults=injector,
                              kill=kill, link_clock=link_clock, prewarm_s=0.0 if lockstep and not lockstep_warm_calls else cfg.prewarm_s)
            loop_ref.append(loop)
            if log is not None:
                log.write("/event", 0.0, {"kind": "start", "text": "race start"})
            res, fifo, loop_cpu = _run_realtime_friendly(loop, meta["rt_priority"], loop_cpu)
            result = {"end": res.end, "winner": res.winner, "duration_s": round(res.t_end, 3),
                      "operator_kill": kill.reason, "rt_fifo": fifo, "loop_cpu": loop_cpu, "track": track.name, "profile": profile.name,
                      "loop": timing_summary(res.timing, dt, [d.name for d in drones]) | {"skipped": res.skipped},
                      "safety_events": res.safety_events, "drones": res.drones,
                      "estimator": {b: dict(c) for b, c in loop.estimator.counters.items()},
                      "laps": {d["name"]: d["laps"] for d in res.drones},
                      "lap_times": {d["name"]: d["lap_times"] for d in res.drones}}
            if log is not None:
                log.write("/race", res.t_end, {"final": True, **loop.race_state(), "end": res.end, "winner": res.winner})
        except BaseException as exc:
            result["error"] = f"{type(exc).__name__}: {exc}"
            if kill.reason is not None:
                result["operator_kill"] = kill.reason
            raise
        finally:
            for link in links:          # every way out: stop every drone first
                try:
                    link.stop()
                except Exception:
                    pass
            if view is not None:
                view.__exit__(None, None, None)
            if settle is not None:
                try:
                    result["drones_final"] = settle()
                except Exception as exc:  # noqa: BLE001
                    result["drones_final_error"] = str(exc)
            for link in links:
                try:
                    link.close()
                except Exception:
                    pass
            if mocap is not None:
                try:
                    mocap.close()
                except Exception:
                    pass
            if injector is not None:
                result["faults"] = injector.log
            if log is not None:
                log.close({k: v for k, v in result.items() if k != "loop"} | {"loop": result.get("loop")})
                result["log"] = str(cfg.log)
    return result


def fly(cfg: FlightConfig, console=None, announce=None) -> dict:
    """`cfrace fly`: real drones (radio:// or udp://) from a mocap system."""
    return run_race(cfg, console=console, announce=announce)
