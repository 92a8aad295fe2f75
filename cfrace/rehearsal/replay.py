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

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cfrace.drone import DroneProfile, load_profile
from cfrace.contract.observations import LAYOUTS
from cfrace.errors import LogError
from cfrace.flight.loop.clock import Tick
from cfrace.flight.config import SafetyConfig
from cfrace.flight.mocap.estimation import PREDICTIONS, PoseEstimator
from cfrace.flight.log.writer import read_log
from cfrace.flight.link.protocol import RecordingLink
from cfrace.flight.loop.flight_loop import FlownDrone, FlightLoop, ObservationBuilder
from cfrace.flight.loop.state import inference_phases
from cfrace.flight.mocap.sources import frame_from_msg, open_mocap
from cfrace.flight.loop.gate_progress import FastRaceProgress
from cfrace.flight.landing.descent import LandingSetup
from cfrace.flight.safety.check import CommandLimits, Fence
from cfrace.track import Track, load_track


class _ReplayClock:
    def __init__(self, ticks: list[dict], dt: float):
        self.ticks, self.dt, self.i = ticks, dt, -1
        self.realtime, self.skipped = False, 0
        self.links: list = []   #: links marked as heard at every tick
        self.kill = None        #: the loop's KillSwitch: the log's last tick ends the replay

    def start(self) -> None:
        self.i = -1

    def wait_next(self) -> Tick:
        self.i = min(self.i + 1, len(self.ticks) - 1)
        if self.i == len(self.ticks) - 1 and self.kill is not None:
            self.kill.request("end of the log")    # (a cut log, a flight ended by the operator)
        m = self.ticks[self.i]
        for link in self.links:
            link.quality.last_rx = self.now()
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


@dataclass(frozen=True)
class _Logged:
    """What a log says of its flight: the set-up, the ticks, the frames and the observations."""

    meta: dict
    track: Track
    profile: DroneProfile
    safety: SafetyConfig
    policies: list
    bodies: list[str]
    rate_hz: float
    laps: int
    ticks: list[dict]
    frames: dict
    obs: dict
    landing: bool          #: the flight landed its drones (/meta "landing"; older logs: a /landing or landing /event)


def _policies(meta: dict, load) -> list:
    """Every drone's policy in drone order (the log's ``policies``, keyed by drone name); a file
    named by several drones is loaded once, as the flight did (batched inference, shared phase)."""
    loaded: dict = {}
    out = []
    for name in meta["policies"]:
        path = meta["policies"][name]["path"]
        if path not in loaded:
            loaded[path] = load(path)
        out.append(loaded[path])
    return out


def _read(path: str | Path, data) -> _Logged:
    """The log's flight; LogError when it cannot be replayed."""
    from cfrace.policy import OnnxPolicy

    meta = data.meta
    try:
        setup = (meta, load_track(meta["track"]), load_profile(meta["profile"]), SafetyConfig(**meta["safety"]),
                 _policies(meta, OnnxPolicy), list(meta["bodies"]),
                 float(meta["rate_hz"]), int(meta["laps"]))
        ticks = [m for _, m in data.messages("/timing")]
        for (t, m) in data.messages("/timing"):
            m["t"] = t
        frames = {int(m["k"]): frame_from_msg(m) for _, m in data.messages("/mocap/pose")}
        if meta.get("latency_prediction", "velocity") not in PREDICTIONS:
            raise ValueError(f"latency_prediction {meta['latency_prediction']!r} is none of {', '.join(PREDICTIONS)}")
    except (KeyError, TypeError, ValueError) as exc:
        raise LogError(f"{path}: cannot replay this log ({type(exc).__name__}: {exc})") from None
    if any(m.get("now") is None for m in ticks):
        raise LogError(f"{path}: no per-tick /timing with 'now' (not a cfrace fly/dry-run log)")
    logged = {}
    last_k = int(ticks[-1]["k"]) if ticks else -1     # a log cut inside a tick: its /obs without its /timing
    for _, m in data.messages("/obs"):
        for body, v in m.items():
            if body != "k" and v is not None and int(m["k"]) <= last_k:
                logged[(int(m["k"]), body)] = np.asarray(v, dtype=np.float32)
    landing = bool(meta.get("landing", data.count("/landing") > 0 or any(
        m.get("kind") == "landing" for _, m in data.messages("/event"))))
    return _Logged(*setup, ticks, frames, logged, landing)


def _loop(lg: _Logged, clock: _ReplayClock, source, links: list, log) -> FlightLoop:
    """The flight loop of the logged flight, with the replay's clock, frames and links."""
    meta, track, profile, safety, pols, bodies = lg.meta, lg.track, lg.profile, lg.safety, lg.policies, lg.bodies
    drones = [FlownDrone(name=n, body=bodies[i], policy=pols[i], layout=LAYOUTS[pols[i].meta["obs_layout"]], link=links[i],
                    meta=pols[i].meta, mass=profile.mass, thrust_curve=profile.thrust_curve,
                    decimation=int(round(lg.rate_hz / pols[i].meta["policy_hz"])), phase=phase)
              for i, (n, phase) in enumerate(zip(meta["policies"], inference_phases(pols)))]
    estimator = PoseEstimator(bodies, stale_after_s=safety.mocap_stale_s, alpha=float(meta.get("velocity_alpha", 0.5)),
                              lead_s=float(meta.get("latency_comp_s", 0.0)),
                              prediction=meta.get("latency_prediction", "velocity"))
    # the race's own timeout (logs before it was in /meta: the last tick) and its landings: after the
    # race's end a drone may fly on on its policy before it lands (failsafe.land_after_race)
    timeout_s = float(meta.get("timeout_s", float(clock.ticks[-1]["t"]) - 1e-9))
    return FlightLoop(drones=drones, mocap=source, estimator=estimator,
                      progress=FastRaceProgress(track.gate_array(), len(drones)),
                      obs_builder=ObservationBuilder(track.gate_corners()), clock=clock,
                      fence=Fence.from_track(track, safety.geofence_margin_m), safety_cfg=safety,
                      laps=lg.laps, timeout_s=timeout_s, log=log, link_clock=clock.now,
                      limits=CommandLimits.from_profile(profile),
                      landing=LandingSetup.for_race(track, profile) if lg.landing else None,
                      hover_start=meta.get("start") == "hover")


def _compare(logged: dict, replayed: dict) -> tuple[int, int, int, float]:
    """(observations compared, mismatched, of those not replayed at all, max |difference| of the
    replayed ones: inf for one of another shape) of the logged against the replayed."""
    compared = mismatched = missing = 0
    max_diff = 0.0
    for key, v in logged.items():
        r = replayed.get(key)
        compared += 1
        if r is None:
            mismatched += 1
            missing += 1
        elif r.shape != v.shape:
            mismatched += 1
            max_diff = float("inf")
        elif not np.array_equal(r, v):
            mismatched += 1
            max_diff = max(max_diff, float(np.max(np.abs(r.astype(np.float64) - v))))
    return compared, mismatched, missing, max_diff


def replay_log(path: str | Path, *, via_replay_source: bool = False) -> dict:
    """Re-run a logged flight lockstep; returns counts and whether every observation matched.

    via_replay_source: read the frames through the mocap source ``replay://LOG?speed=0`` (one
    frame per read) instead of by tick index; needs a log with exactly one frame per tick (a
    lockstep dry-run without mocap faults)."""
    lg = _read(path, read_log(path))
    if not lg.ticks:      # a cfrace log cut before its first tick: nothing to compare (exit code 1)
        return {"log": str(path), "ticks": 0, "frames": len(lg.frames), "observations": 0, "mismatched": 0,
                "not_replayed": 0, "max_abs_diff": 0.0, "identical": False}
    clock = _ReplayClock(lg.ticks, 1.0 / lg.rate_hz)
    source = _LogFrames(lg.frames, clock)
    if via_replay_source:
        if sorted(lg.frames) != [int(m["k"]) for m in lg.ticks]:
            raise LogError(f"{path}: not one mocap frame per tick; replay it by tick (without via_replay_source)")
        source = open_mocap(f"replay://{path}?speed=0", bodies=lg.bodies)
        source.open()
    links = [RecordingLink(f"null://{n}", clock=clock.now) for n in lg.meta["policies"]]
    for link in links:
        link.connect()
    clock.links = links   # links never go silent in a replay: keep them "heard" every tick
    collect = _Collect()
    loop = _loop(lg, clock, source, links, collect)
    clock.kill = loop.kill
    loop.run()
    compared, mismatched, missing, max_diff = _compare(lg.obs, collect.obs)
    return {"log": str(path), "ticks": len(lg.ticks), "frames": len(lg.frames), "observations": compared,
            "mismatched": mismatched, "not_replayed": missing, "max_abs_diff": max_diff,
            "identical": compared > 0 and mismatched == 0}
