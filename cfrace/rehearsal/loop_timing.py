"""`cfrace bench loop`: the flight loop's timing, real time, N drones (2 by default) at 100 Hz against the sim.

Set-up as in a real flight: the simulated Crazyflies run in their own process (`cfrace sim
serve`, like real drones they do not share the flight process), the flight process runs the
unchanged `cfrace fly` code: the real cflib client over UDP, the `sim://` pose stream as mocap,
the flight log written every tick. Policies (--policies): "paper" (default), the linear hold
controller inside an MLP of the paper's actor size ([512, 512, 256, 128]): inference costs what
the paper's actor costs and the drones fly the whole run; or "shipped", the track's shipped
ours/ds policies (smaller actors; a crashed drone stops its samples).
Goals on this machine: compute p99 <= 1 ms, period jitter p99 <= 0.5 ms, inference <= 0.2 ms.
"""

from __future__ import annotations

import os
import random
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from cfrace.errors import CfraceError, LinkError, PolicyError
from cfrace.flight.loop import realtime
from cfrace.flight.loop.clock import RealClock
from cfrace.flight.config import FlightConfig
from cfrace.flight.log.timing import ms_stats, periods
from cfrace.flight.loop.realtime import other_cpus, resolve_loop_cpu
from cfrace.flight.loop.race import run_race
from cfrace.flight.setup import real_io, resolve_race, training_profile
from cfrace.paths import POLICIES_DIR
from cfrace.track import load_track

GOALS_MS = {"compute_p99_ms": 1.0, "period_jitter_p99_ms": 0.5, "inference_p99_ms": 0.2}


def _free_base_port(drones: int = 2) -> int:
    """A base port with base-1 .. base+drones-1 free (pose port, the drones), below the kernel's
    ephemeral range so that other programs' automatically assigned ports cannot take them."""
    rng = random.Random()
    for _ in range(100):
        base = rng.randrange(20001, 30000)
        socks = []
        try:
            for p in range(base - 1, base + drones):
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                socks.append(s)
                s.bind(("127.0.0.1", p))
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise LinkError("no free UDP ports for the simulated drones")


def bench_policies(track: str, workdir: Path, which: str = "paper") -> tuple[str, str, str]:
    """which: "paper" (the hold controller inside the paper's actor size, flies the whole run) or
    "shipped" (policies/ours_TRACK.onnx vs ds_TRACK.onnx: real inference cost; the run ends early
    if both crash)."""
    if which == "shipped":
        ours, ds = POLICIES_DIR / f"ours_{track}.onnx", POLICIES_DIR / f"ds_{track}.onnx"
        if not (ours.exists() and ds.exists()):
            raise PolicyError(f"no shipped policies {ours.name} and {ds.name} in {POLICIES_DIR}")
        return str(ours), str(ds), "shipped ours vs ds"
    from cfrace.rehearsal.hold_policy import make_sized_hold_policy

    ego = make_sized_hold_policy(workdir / "ego.onnx", "race42", track, False)
    opp = make_sized_hold_policy(workdir / "opp.onnx", "solo36", track, False, seed=1)
    return str(ego), str(opp), "hold controller in a [512, 512, 256, 128] MLP"


def bare_loop(seconds: float, *, rt_priority="auto", loop_cpu="auto", prewarm_s: float = 0.003,
              dt: float = 0.01) -> dict:
    """The machine's floor: a 100 Hz loop with no work at all, on the CPU and at the priority the
    flight loop gets, waiting exactly as the flight loop waits (RealClock.wait_next with an empty
    warm-up). Its tick lateness and period jitter are what any Python loop gets
    here; `cfrace bench loop` prints the flight loop's beside them. Returns late_ms and
    period_jitter_ms (as timing_summary) plus loop_cpu and rt_fifo."""
    cpu = realtime.resolve_loop_cpu(loop_cpu)
    pinned = realtime.pin_loop_thread(cpu)
    fifo = realtime.set_fifo(realtime.resolve_rt_priority(rt_priority))
    nothing = (lambda: None) if prewarm_s > 0 else None
    clock = RealClock(dt)
    ticks = []
    try:
        clock.start()
        while len(ticks) < int(round(seconds / dt)):
            ticks.append(clock.wait_next(nothing, prewarm_s))
    finally:
        realtime.restore_scheduler(fifo)
        realtime.restore_affinity(pinned)
    period = periods([t.wall for t in ticks])
    return {"ticks": len(ticks), "late_ms": ms_stats([t.late_s for t in ticks]),
            "period_jitter_ms": ms_stats(np.abs(period - dt)), "loop_cpu": cpu, "rt_fifo": fifo is not None}


def bench_loop(duration_s: float = 10.0, *, track: str = "lemniscate", profile: str | None = None,
               log: bool = True, rt_priority="auto", policies: str = "paper",
               prewarm_s: float = 0.003, latency_comp_s: float | None = None, loop_cpu="auto",
               floor_s: float = 0.0, pose_stream: bool = True, drones: int = 2, foxglove: bool = False,
               scene: bool = True) -> dict:
    """Run the loop for duration_s against a `cfrace sim serve` subprocess; timing summary dict.
    profile: simulated and flown drone profile; default: the shipped policies' training profile
    (they crash on another one), cf21bl for the paper-size hold controller.
    loop_cpu: as `cfrace fly` (cfrace.flight.loop.realtime); when the loop thread is pinned, the
    simulated drones run on the other CPUs (real drones compute on their own hardware).
    floor_s > 0: first, with the simulated drones already running, the machine's floor
    (``bare_loop``) for that long, on the same CPU and priority ("floor" in the result).
    drones > 2: the two policies alternate over the drones (ego, opp, ego, opp, ...): each runs
    in one batched inference call for its drones (cfrace.flight.loop.tick).
    foxglove: serve the flight live to Foxglove (a free port), as `cfrace fly --foxglove`; scene:
    the Foxglove scene in the log (off: the log of JSON records alone)."""
    pinned = resolve_loop_cpu(loop_cpu)
    with tempfile.TemporaryDirectory(prefix="cfrace-bench-") as tmp:
        work = Path(tmp)
        ego, opp, kind = bench_policies(track, work, policies)
        if profile is None:
            profile = training_profile(load_track(track), ego, False) if policies == "shipped" else "cf21bl"
        base = _free_base_port(drones)
        cmd = [sys.executable, "-c", "from cfrace.cli.main import main; main()", "sim", "serve", "--track", track,
               "--drones", str(drones),
               "--port", str(base), "--profile", profile,
               "--no-obstacles"]   # as the race: the policies fly the track without obstacles
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            if pinned is not None:   # before it starts its threads (they inherit it): Python is still starting
                os.sched_setaffinity(proc.pid, other_cpus(pinned))
            cfg = _bench_config(track, ego, opp, drones, base, profile=profile, timeout_s=duration_s,
                                log=(work / "bench.mcap") if log else None, rt_priority=rt_priority,
                                prewarm_s=prewarm_s, latency_comp_s=latency_comp_s, loop_cpu=loop_cpu,
                                pose_stream=pose_stream, landing=pose_stream,
                                foxglove_port=0 if foxglove else None, foxglove_scene=scene)
            floor = bare_loop(floor_s, rt_priority=rt_priority, loop_cpu=loop_cpu, prewarm_s=prewarm_s) \
                if floor_s > 0 else None
            try:
                result = run_race(resolve_race(cfg), real_io(cfg)).to_json()
                sim_cpus = sorted(os.sched_getaffinity(proc.pid)) if hasattr(os, "sched_getaffinity") else None
            except CfraceError as exc:
                if proc.poll() is not None:   # the simulator process died: say why
                    raise LinkError(f"cfrace sim serve exited: {proc.stderr.read().strip()[-300:]}") from None
                raise exc
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
    loop = result["loop"]
    met = {k: (loop[k] is not None and loop[k] <= v) for k, v in GOALS_MS.items()}
    return {"duration_s": duration_s, "pose_stream": pose_stream, "drones": drones, "policies": kind, "profile": profile, "latency_comp_s": cfg.latency_comp, "prewarm_s": prewarm_s, "foxglove": foxglove, "scene": scene, "end": result["end"], "loop": loop, "rt_fifo": result["rt_fifo"],
            "loop_cpu": result["loop_cpu"], "sim_serve_cpus": sim_cpus, "floor": floor,
            "goals_ms": GOALS_MS, "goals_met": met, "safety_events": result["safety_events"],
            "cpu_count": os.cpu_count(), "load_avg": os.getloadavg(), "time": time.strftime("%Y-%m-%d %H:%M:%S")}


def _bench_config(track: str, ego: str, opp: str, drones: int, base: int, **options) -> FlightConfig:
    """The benchmark's race: ``drones`` simulated drones on UDP ports base.. (mocap on base - 1),
    the two policies alternating over them, laps enough never to finish."""
    specs = tuple((ego, opp)[i % 2] for i in range(drones))
    return FlightConfig(track=track, ego=ego, opp=opp, policies=specs if drones > 2 else (), laps=1000,
                        uris=tuple(f"udp://127.0.0.1:{base + i}" for i in range(drones)),
                        mocap=f"sim://127.0.0.1:{base - 1}", quiet=True, mocap_timeout_s=15.0,
                        connect_timeout_s=15.0, **options)


def compare_pose_stream(duration_s: float = 10.0, rounds: int = 1, **options) -> dict:
    """The loop without (and so without landing: today's stop) and with the pose stream (each drone's
    mocap pose sent to it every frame),
    alternating, ``rounds`` times each, in one run: the figures of every run and, per condition, the
    median over its runs of compute p50/p99 (ms) and of the packets per second the flight process
    hands the links (setpoints, and poses when streaming)."""
    runs = {False: [], True: []}
    for _ in range(rounds):
        for stream in (False, True):
            runs[stream].append(bench_loop(duration_s, pose_stream=stream, **options))

    def summary(rs: list) -> dict:
        def med(f):
            vals = [f(r) for r in rs if f(r) is not None]
            return round(float(np.median(vals)), 4) if vals else None
        return {"compute_p50_ms": med(lambda r: r["loop"]["compute_ms"]["p50"]),
                "compute_p99_ms": med(lambda r: r["loop"]["compute_ms"]["p99"]),
                "compute_cpu_p50_ms": med(lambda r: r["loop"]["compute_cpu_ms"]["p50"]),
                "period_jitter_p99_ms": med(lambda r: r["loop"]["period_jitter_ms"]["p99"]),
                "setpoints_per_s": med(lambda r: r["loop"]["setpoints_sent"] / r["duration_s"]),
                "poses_per_s": med(lambda r: r["loop"]["poses_sent"] / r["duration_s"])}
    off, on = summary(runs[False]), summary(runs[True])
    ratio = {k: (round(on[k] / off[k], 3) if off[k] and on[k] is not None else None)
             for k in ("compute_p50_ms", "compute_p99_ms", "compute_cpu_p50_ms")}
    return {"without": off, "with": on, "ratio_with_over_without": ratio, "rounds": rounds,
            "duration_s": duration_s, "runs": {"without": runs[False], "with": runs[True]},
            "load_avg": os.getloadavg(), "time": time.strftime("%Y-%m-%d %H:%M:%S")}


#: (label, key in the loop figures, quantile) compared by `bench loop --foxglove`
FOXGLOVE_FIGURES = (("compute p50", "compute_ms", "p50"), ("compute p99", "compute_ms", "p99"),
                    ("compute CPU p50", "compute_cpu_ms", "p50"), ("period jitter p99", "period_jitter_ms", "p99"),
                    ("tick start late p99", "late_ms", "p99"))
#: the configurations `bench loop --foxglove` compares: (name, Foxglove scene in the log, live server)
FOXGLOVE_CONFIGS = (("plain log", False, False), ("scene in log", True, False), ("scene + live", True, True))


def compare_foxglove(duration_s: float, rounds: int, on_run=None, **options) -> dict:
    """The loop with the log of JSON records alone, with the Foxglove scene in it and with the scene
    served live too, alternating ``rounds`` times; per figure the medians (ms) and their ratios to
    the plain log. ``on_run(round, name, result)`` after each run."""
    runs: dict[str, list] = {name: [] for name, _, _ in FOXGLOVE_CONFIGS}
    for i in range(rounds):
        for name, scene, live in FOXGLOVE_CONFIGS:
            r = bench_loop(duration_s, floor_s=0.0, foxglove=live, scene=scene, **options)
            runs[name].append(r)
            if on_run is not None:
                on_run(i, name, r)
    names = [n for n, _, _ in FOXGLOVE_CONFIGS]
    doc = {"rounds": rounds, "duration_s": duration_s, "configs": names, "figures": {}, "runs": runs}
    for label, key, q in FOXGLOVE_FIGURES:
        med = [statistics.median(r["loop"][key][q] for r in runs[n]) for n in names]
        doc["figures"][label] = {"ms": dict(zip(names, med)),
                                 "ratio_to_plain": {n: (m / med[0] if med[0] else None) for n, m in zip(names[1:], med[1:])}}
    return doc


def landing_tick_cpu(drones: int = 8, track: str = "complex", duration_s: float = 10.0) -> dict:
    """bench_loop (no floor) with the CPU of each tick of cfrace.flight.loop.tick.TickCore.step recorded
    (time.thread_time: the loop thread's CPU, not the machine's load). At the bench's time-out every drone
    starts landing in one tick. {"drones", "track", "landing_ticks_cpu_ms": [[CPU ms, tick, drones
    landing], ...] slowest first, "racing_cpu_ms": {"p50", "p99", "max"}}."""
    from cfrace.flight.loop.tick import TickCore

    ticks = []                       # (cpu s, k, drones landing)
    step = TickCore.step

    def timed(self, t_in, *a, **kw):
        c0 = time.thread_time()
        out = step(self, t_in, *a, **kw)
        ticks.append((time.thread_time() - c0, t_in.k, sum(d.landing is not None for d in self.drones)))
        return out

    TickCore.step = timed
    try:
        bench_loop(duration_s, track=track, drones=drones, floor_s=0.0)
    finally:
        TickCore.step = step
    landing = sorted((t for t in ticks if t[2]), reverse=True)
    racing = np.array([t[0] for t in ticks if not t[2]]) * 1e3
    return {"drones": drones, "track": track,
            "landing_ticks_cpu_ms": [[round(c * 1e3, 3), k, n] for c, k, n in landing],
            "racing_cpu_ms": {"p50": float(np.median(racing)), "p99": float(np.percentile(racing, 99)),
                              "max": float(racing.max())}}
