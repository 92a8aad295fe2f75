"""Replay a flight log through the flight loop, lockstep, and check that it reproduces the logged
observations exactly (`cfrace sim replay LOG`).

The log holds everything the observations depend on: each mocap frame with the tick it arrived
in (/mocap/pose "k"), each tick's loop-clock time (/timing "now", "t"), the policies, track,
bodies and limits (/meta). The replay feeds the same frames at the same ticks and times into the
same estimator, race progress and observation function, with links to nowhere, and compares
every logged /obs vector bit for bit. (Drones that the original flight stopped for reasons a
replay cannot see, e.g. a lost link, keep computing observations in the replay; only the logged
ones are compared.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cfrace.drone import load_profile
from cfrace.env.observations import LAYOUTS
from cfrace.errors import LogError
from cfrace.flight.clock import Tick
from cfrace.flight.config import DRONE_NAMES, SafetyConfig
from cfrace.flight.estimator import PoseEstimator
from cfrace.flight.flightlog import read_log
from cfrace.flight.link import RecordingLink
from cfrace.flight.loop import Drone, FlightLoop, ObservationBuilder
from cfrace.flight.mocap import frame_from_msg
from cfrace.flight.progress import FastRaceProgress
from cfrace.flight.safety import Fence
from cfrace.track import load_track


class _ReplayClock:
    def __init__(self, ticks: list[dict], dt: float):
        self.ticks, self.dt, self.i = ticks, dt, -1
        self.realtime, self.skipped = False, 0

    def start(self) -> None:
        self.i = -1

    def wait_next(self) -> Tick:
        self.i = min(self.i + 1, len(self.ticks) - 1)
        m = self.ticks[self.i]
        return Tick(int(m["k"]), float(m["t"]), float(m["late_s"] or 0.0), int(m["skipped"] or 0), float(m["t"]))

    def now(self) -> float:
        return float(self.ticks[max(self.i, 0)]["now"])

    @property
    def k(self) -> int:
        return int(self.ticks[max(self.i, 0)]["k"])

    def stall(self, seconds: float) -> None:
        pass


class _LogFrames:
    """A mocap source that returns the frame logged at the clock's current tick."""

    name = "replay"

    def __init__(self, frames: dict, clock: _ReplayClock):
        self.frames, self.clock = frames, clock

    def read(self, timeout_s: float = 0.0):
        return self.frames.get(self.clock.k)

    def close(self) -> None:
        pass


class _Collect:
    """Stands in for the FlightLog: keeps the replayed /obs."""

    def __init__(self):
        self.obs: dict[tuple[int, str], np.ndarray] = {}

    def write(self, topic: str, t: float, msg: dict) -> None:
        if topic == "/obs":
            k = msg["k"]
            for body, v in msg.items():
                if body != "k" and v is not None:
                    self.obs[(k, body)] = np.asarray(v, dtype=np.float32)


def replay_log(path: str | Path, *, via_replay_source: bool = False) -> dict:
    """Re-run a logged flight lockstep; returns counts and whether every observation matched.

    via_replay_source: read the frames through the mocap source ``replay://LOG?speed=0`` (one
    frame per read) instead of by tick index; needs a log with exactly one frame per tick (a
    lockstep dry-run without mocap faults)."""
    from cfrace.policy import OnnxPolicy

    data = read_log(path)
    meta = data.meta
    try:
        track = load_track(meta["track"])
        profile = load_profile(meta["profile"])
        bodies = list(meta["bodies"])
        dt = 1.0 / float(meta["rate_hz"])
        safety = SafetyConfig(**meta["safety"])
        pols = [OnnxPolicy(meta["policies"][n]["path"]) for n in DRONE_NAMES]
        ticks = [m for _, m in data.messages("/timing")]
        for (t, m) in data.messages("/timing"):
            m["t"] = t
        frames = {int(m["k"]): frame_from_msg(m) for _, m in data.messages("/mocap/pose")}
    except (KeyError, TypeError, ValueError) as exc:
        raise LogError(f"{path}: cannot replay this log ({type(exc).__name__}: {exc})") from None
    if not ticks or any(m.get("now") is None for m in ticks):
        raise LogError(f"{path}: no per-tick /timing with 'now' (not a cfrace fly/dry-run log)")
    logged = {}
    for _, m in data.messages("/obs"):
        for body, v in m.items():
            if body != "k" and v is not None:
                logged[(int(m["k"]), body)] = np.asarray(v, dtype=np.float32)
    clock = _ReplayClock(ticks, dt)
    source = _LogFrames(frames, clock)
    if via_replay_source:
        from cfrace.flight.mocap import open_mocap

        if sorted(frames) != [int(m["k"]) for m in ticks]:
            raise LogError(f"{path}: not one mocap frame per tick; replay it by tick (without via_replay_source)")
        source = open_mocap(f"replay://{path}?speed=0", bodies=bodies)
        source.open()
    links = [RecordingLink(f"null://{n}", clock=clock.now) for n in DRONE_NAMES]
    for link in links:
        link.connect()
    drones = [Drone(name=n, body=bodies[i], policy=pols[i], layout=LAYOUTS[pols[i].meta["obs_layout"]], link=links[i],
                    meta=pols[i].meta, mass=profile.mass, thrust_curve=profile.thrust_curve,
                    decimation=int(round(float(meta["rate_hz"]) / pols[i].meta["policy_hz"])), phase=i)
              for i, n in enumerate(DRONE_NAMES)]
    collect = _Collect()
    loop = FlightLoop(drones=drones, mocap=source, estimator=PoseEstimator(bodies, stale_after_s=safety.mocap_stale_s,
                                                                         alpha=float(meta.get("velocity_alpha", 0.5)),
                                                                         lead_s=float(meta.get("latency_comp_s", 0.0))),
                      progress=FastRaceProgress(track.gate_array(), len(drones)),
                      obs_builder=ObservationBuilder(track.gate_corners()), clock=clock,
                      fence=Fence.from_track(track, safety.geofence_margin_m), safety_cfg=safety,
                      laps=int(meta["laps"]), timeout_s=float(ticks[-1]["t"]) - 1e-9, log=collect,
                      link_clock=clock.now)
    # links never go silent in a replay: keep them "heard" every tick
    orig_wait = clock.wait_next

    def wait_next(*args):
        tick = orig_wait(*args)
        for link in links:
            link.quality.last_rx = clock.now()
        return tick
    clock.wait_next = wait_next
    loop.run()
    compared = mismatched = 0
    max_diff = 0.0
    for key, v in logged.items():
        r = collect.obs.get(key)
        compared += 1
        if r is None or r.shape != v.shape or not np.array_equal(r, v):
            mismatched += 1
            if r is not None and r.shape == v.shape:
                max_diff = max(max_diff, float(np.max(np.abs(r.astype(np.float64) - v))))
            else:
                max_diff = float("inf")
    return {"log": str(path), "ticks": len(ticks), "frames": len(frames), "observations": compared,
            "mismatched": mismatched, "max_abs_diff": max_diff, "identical": compared > 0 and mismatched == 0}
