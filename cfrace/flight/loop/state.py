"""The flight loop's state: the drones as the loop flies them, the kill switch, the observation
builder, the per-tick timing figures and the result of a race."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cfrace.contract.actions import SetpointMap
from cfrace.contract.observations import ObsLayout, build_observation


class KillSwitch:
    """Set by signal handlers (or anyone): the next tick stops every drone and ends the loop."""

    def __init__(self):
        self.reason: str | None = None
        self.land: str | None = None      #: the operator's "land now" (soft: every drone lands)

    def request(self, reason: str) -> None:
        if self.reason is None:
            self.reason = reason

    def request_land(self, reason: str) -> None:
        if self.land is None:
            self.land = reason


@dataclass
class FlownDrone:
    """One racing drone in the loop (mutable runtime state)."""

    name: str                  #: "ego" / "opp"
    body: str                  #: mocap body name
    policy: object             #: callable obs (1, D) float32 -> (1, 4) actions
    layout: ObsLayout
    link: object               #: cfrace.flight.link.protocol.Link
    meta: dict                 #: policy metadata
    mass: float                #: kg, flown drone (thrust in N = weights x m g)
    thrust_curve: object       #: profile.thrust_curve
    decimation: int = 2        #: loop ticks per policy step
    phase: int = 0             #: the policy runs on ticks with k % decimation == phase
    stopped: bool = False
    stop_kind: str = ""
    stop_t: float = float("nan")
    stop_k: int = -1
    frozen_pos: np.ndarray | None = None
    action: np.ndarray | None = None   #: (4,) last policy output; None before the first inference
    obs: np.ndarray | None = None
    thrust_n: float = 0.0
    rates_dps: tuple = (0.0, 0.0, 0.0)   #: roll, pitch, yaw rate setpoint, deg/s
    counts: int = 0
    speed_max: float = 0.0
    speed_sum: float = 0.0
    speed_n: int = 0
    setpoint_map: SetpointMap | None = None   #: built from meta, mass and thrust_curve
    landing: object = None             #: cfrace.flight.landing.descent.LandingPilot while the drone lands
    landing_result: dict | None = None   #: why it landed, its spot, its touchdown (or how the landing ended)

    def __post_init__(self):
        if self.setpoint_map is None:
            self.setpoint_map = SetpointMap(self.mass, self.meta["max_thrust_weights"], self.meta["max_rates_deg"],
                                            self.thrust_curve)


class ObservationBuilder:
    """The training observation (cfrace.contract.observations.build_observation, the same function)
    from estimates, on float32 numpy arrays: no torch dispatch in the tick. Bit-identical to the
    env's torch observations on the same states (tests/test_flight_core.py); 87 us instead of 428 us
    per call on one-drone torch tensors (p50 in the real-time loop, docs/benchmarks.md)."""

    def __init__(self, gate_corners: np.ndarray):
        self.corners = np.ascontiguousarray(np.asarray(gate_corners, dtype=np.float32))  # (G, 4, 3)
        self._no_opp = np.zeros(6)

    def __call__(self, layout: ObsLayout, est, target: int, opp=None) -> np.ndarray:
        st = self._state(layout, est, opp)
        pos, vel, rot = st[0:3], st[3:6], st[6:15].reshape(3, 3)
        opp_pos, opp_vel = (st[15:18], st[18:21]) if layout.opponent else (None, None)
        return build_observation(pos, vel, rot, int(target), self.corners, layout, opp_pos, opp_vel)

    def many(self, layout: ObsLayout, ests: list, targets: list[int], opps: list) -> np.ndarray:
        """(M, D): row m is ``self(layout, ests[m], targets[m], opps[m])``, bit for bit, in one
        build_observation call (the drones of one policy in a field: a third of the cost of M calls)."""
        st = np.stack([self._state(layout, e, o) for e, o in zip(ests, opps)])
        pos, vel, rot = st[:, 0:3], st[:, 3:6], st[:, 6:15].reshape(-1, 3, 3)
        opp_pos, opp_vel = (st[:, 15:18], st[:, 18:21]) if layout.opponent else (None, None)
        return build_observation(pos, vel, rot, np.asarray(targets, np.int64), self.corners, layout, opp_pos, opp_vel)

    def _state(self, layout: ObsLayout, est, opp) -> np.ndarray:
        """The float32 state an observation is built from: pos, vel, rot (row-major), [opponent pos, vel]."""
        o = (opp.pos, opp.vel) if layout.opponent else (self._no_opp,)
        return np.concatenate([est.pos, est.vel, np.ravel(est.rot), *o]).astype(np.float32)


@dataclass
class LoopResult:
    end: str                         #: "finished", "all_stopped", "timeout", "operator_kill", "loop_overrun"
    winner: str                      #: drone name or "draw"
    t_end: float
    ticks: int
    skipped: int
    timing: dict                     #: arrays: late, period, compute, compute_cpu, infer + obs (per drone)
    safety_events: list
    drones: list


class TickTimes:
    """The per-tick timing figures of a race (LoopResult.timing), appended after each send."""

    def __init__(self, n: int):
        self.late, self.start, self.compute, self.cpu, self.warm, self.warm_n = [], [], [], [], [], []
        self.infer, self.obs = [[] for _ in range(n)], [[] for _ in range(n)]

    def add(self, tick, compute: float, cpu: float, warm_s: float, warm_n: int, infer: list, obs_t: list) -> None:
        self.cpu.append(cpu)
        self.late.append(tick.late_s)
        self.start.append(tick.wall)
        self.compute.append(compute)
        self.warm.append(warm_s if warm_n else np.nan)
        self.warm_n.append(warm_n)
        for i in range(len(self.infer)):
            self.infer[i].append(infer[i])
            self.obs[i].append(obs_t[i])

    def arrays(self) -> dict:
        from cfrace.flight.log.timing import periods   # the one definition of a period

        return {"late": np.asarray(self.late), "period": periods(self.start),
                "compute": np.asarray(self.compute), "compute_cpu": np.asarray(self.cpu),
                "prewarm": np.asarray(self.warm), "prewarm_calls": np.asarray(self.warm_n),
                "infer": [np.asarray(x) for x in self.infer], "obs": [np.asarray(x) for x in self.obs]}


_RACE_FIELDS = ("duration_s", "operator_kill", "rt_fifo", "loop_cpu", "track", "profile", "loop", "safety_events",
                "drones", "estimator", "laps", "lap_times")
_WAY_OUT_FIELDS = ("error", "drones_final", "drones_final_error", "faults", "log", "log_error", "sim", "hover_start",
                   "landings", "separation_at_stop")


@dataclass
class RaceResult:
    """What a race (`cfrace fly`, `cfrace sim dry-run`) came to; ``to_json()`` is its JSON document
    (docs/flight.md). The race fields are set when the loop ran to an end, the way-out fields when
    they apply; ``end`` is "error" when the race did not get to run or raised."""

    end: str = "error"            #: finished, all_stopped, timeout, operator_kill, a stop_all safety kind, error
    winner: str = "draw"          #: ego, opp or draw
    duration_s: float | None = None
    operator_kill: str | None = None   #: SIGINT / SIGTERM when the operator ended the race
    rt_fifo: bool = False
    loop_cpu: int | None = None
    track: str = ""
    profile: str = ""
    loop: dict | None = None      #: timing figures (cfrace.flight.log.timing.loop_figures) plus skipped
    safety_events: list = field(default_factory=list)
    drones: list = field(default_factory=list)       #: per drone: laps, lap times, stop, speeds, link
    estimator: dict = field(default_factory=dict)    #: per body: frames, occluded, outliers, ...
    laps: dict = field(default_factory=dict)         #: drone name -> laps
    lap_times: dict = field(default_factory=dict)    #: drone name -> lap times s
    error: str | None = None
    drones_final: list | None = None                 #: the simulated drones' state after the race (dry-run)
    drones_final_error: str | None = None
    faults: list | None = None                       #: what the fault injection did (dry-run)
    log: str | None = None                           #: the flight log's path
    log_error: str | None = None                     #: why the flight log is incomplete (a write error)
    sim: dict | None = None                          #: the simulated drones' server figures (real-time dry-run)
    hover_start: dict | None = None                  #: --start hover: how well the drones held their start
    landings: dict | None = None                     #: drone name -> its landing (reason, spot, touchdown) or None
    #: pairs closer than safety.min_separation_m when every drone was stopped (cfrace.flight.safety.check)
    separation_at_stop: list | None = None

    def to_json(self) -> dict:
        out = {"end": self.end, "winner": self.winner}
        if self.loop is not None:
            out.update({k: getattr(self, k) for k in _RACE_FIELDS})
        elif self.operator_kill is not None:
            out["operator_kill"] = self.operator_kill
        out.update({k: getattr(self, k) for k in _WAY_OUT_FIELDS if getattr(self, k) is not None})
        return out


def inference_phases(policies) -> list[int]:
    """The tick phase of each drone's inference (it infers on ticks k with k % decimation == phase).
    Two drones: 0 and 1, staggered (each tick runs one policy). More: one phase per distinct policy
    in order of appearance, so the drones flying the same policy infer on the same tick in one
    batched call and the distinct policies share the ticks out (ours, ours, ds, ds: 0, 0, 1, 1)."""
    if len(policies) == 2:
        return [0, 1]
    order: dict[int, int] = {}
    for p in policies:
        order.setdefault(id(p), len(order))
    return [order[id(p)] for p in policies]
