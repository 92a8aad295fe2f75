"""Batched evaluation rollouts: W worlds x D drones (runs or races) flown at once by ONNX policies.

Every (world, drone) slot is assigned a policy (or -1: motors off, a drone that drops and crashes,
the "crashed opponent" of the speed comparison). Each step: for each policy, the observations of
all its slots are built with the layout its metadata names (opponent block from the other drone of
the world; with more than two drones from the one the opponent rule picks, the policy's own
``opponent_rule`` metadata or the race's; from a parked opponent when flying alone), ONE onnxruntime call gives all their
actions, the action map uses the policy's own constants; then the simulator steps 10 x 2 ms.
Nominal parameters (no domain randomisation), default crash rules.

A world stops racing once a drone completed the laps or every drone is down (crashed or finished);
with ``until_all`` (fields of more than two: the finishing order) only once every drone is down.
The loop ends when every world has stopped or at the time limit.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from cfrace.contract import POLICY_DT
from cfrace.drone import DroneProfile
from cfrace.contract.actions import FIRMWARE_MIN_THRUST_COUNTS, action_to_command
from cfrace.contract.observations import DEFAULT_OPPONENT_RULE, build_observation, choose_opponents, polyline, track_position
from cfrace.env.race_env import MOCAP_DT, RaceEnv
from cfrace.loopmodel import predict_commanded
from cfrace.sim.collisions import CONTACT_MARGIN
from cfrace.errors import ConfigError
from cfrace.evaluate.entrants import Entrant
from cfrace.evaluate.metrics import RunSummary, summarize
from cfrace.sim.simulator import Simulator
from cfrace.track import Track

SUBSTEPS = 10                 #: 10 x 2 ms = one 50 Hz policy step
LAP_TIME_LIMIT_S = 15.0       #: default time limit per lap
OFF_ACTION = (-1.0, 0.0, 0.0, 0.0)  #: motors off: zero thrust, zero rates


@dataclass
class RacesRun:
    """What a set of races was run with (the head of every race result)."""
    track: str
    obstacles: bool
    races: int
    laps: int
    seed: int
    time_limit_s: float


@dataclass(frozen=True)
class Starts:
    pos: torch.Tensor     # (W, D, 3) m
    quat: torch.Tensor    # (W, D, 4) wxyz
    target: torch.Tensor  # (W, D) int64 first target gate


@dataclass
class Recording:
    """Per-step arrays (T steps, W worlds, D drones); positions only for the recorded worlds."""

    t: np.ndarray             # (T,) s, end time of each step
    active: np.ndarray        # (T, W, D) bool
    speed: np.ndarray         # (T, W, D) m/s
    lap_stamp: np.ndarray     # (T, W, D) s, nan without a lap completion
    contact: np.ndarray       # (T, W, D) bool
    crashed_now: np.ndarray   # (T, W, D) bool
    reason: np.ndarray        # (T, W, D) int8
    crashed: np.ndarray       # (T, W, D) bool, crashed at the end of the step (sticky)
    pos: np.ndarray           # (T, K, D, 3) m, worlds ``recorded``
    recorded: tuple[int, ...]
    nan_actions: np.ndarray   # (W, D) int, steps with non-finite actions (replaced by motors off)
    laps: int
    wall_s: float = 0.0
    track_pos: np.ndarray | None = None      # (T, K, D) m along the race line, worlds ``recorded``
    pair_contacts: np.ndarray | None = None  # (W, D, D) int, new drone-drone contacts of each pair while racing
    crash_partner: np.ndarray | None = None  # (W, D) int, the drone touched at the crash step (-1: none)
    gates_passed: np.ndarray | None = None   # (W, D) int, gates passed at the end

    def summary(self) -> RunSummary:
        return summarize(self.active, self.speed, self.lap_stamp, self.contact, self.crashed_now, self.reason,
                         self.laps, POLICY_DT)

    @property
    def steps(self) -> int:
        return int(self.t.shape[0])


def start_poses(track: Track, profile: DroneProfile, n: int, drones: int, obstacles: bool, seed: int,
                swap_pairs: bool = False, start: str = "gate") -> Starts:
    """n start configurations from the training spawn (RaceEnv.spawn): ``start`` "gate" (in front of
    a random gate, facing it, that gate is the first target) or "ground" (on the floor before gate
    0, the training's ground starts). With ``swap_pairs`` (2 drones) start i uses configuration
    i // 2, with the two slots swapped for odd i (half the races swap)."""
    if start not in ("gate", "ground"):
        raise ConfigError(f"--start: gate or ground, got {start!r}")
    env = RaceEnv(track, profile, num_envs=1, method="ours" if drones >= 2 else "ds", obstacles=obstacles,
                  seed=seed, randomize=False, start=start, drones=drones if drones > 2 else None)
    m = (n + 1) // 2 if swap_pairs else n
    pos, quat, gate = env.spawn(m)
    target = gate.unsqueeze(-1).expand(m, drones).clone()
    if swap_pairs:
        idx = torch.arange(n) // 2
        pos, quat, target = pos[idx].clone(), quat[idx].clone(), target[idx].clone()
        odd = torch.arange(n) % 2 == 1
        pos[odd], quat[odd] = pos[odd].flip(1), quat[odd].flip(1)
    return Starts(pos.cpu(), quat.cpu(), target.cpu())


def parked_opponents(track: Track, profile: DroneProfile, starts: Starts) -> torch.Tensor:
    """(W, 3) where a multi-agent policy flying alone sees its opponent in each world: crashed at the
    start, resting on the floor in the slot beside the drone's start (the track's side-by-side
    ``opponent_offset`` to its left in even worlds, to its right in odd ones), zero velocity. That is
    what a race shows once the opponent crashes at the start: a crashed drone stays where it fell
    (cfrace.env.race_env), so no training race shows an opponent anywhere else at rest."""
    yaw = torch.as_tensor(track.gate_array()[:, 3], dtype=torch.float32)[starts.target[:, 0]]
    side = torch.stack([-torch.sin(yaw), torch.cos(yaw)], -1)                        # (W, 2)
    sign = 1.0 - 2.0 * (torch.arange(yaw.shape[0]) % 2).to(torch.float32)
    out = torch.empty(yaw.shape[0], 3)
    out[:, :2] = starts.pos[:, 0, :2] + side * (sign * track.spawn.opponent_offset).unsqueeze(-1)
    out[:, 2] = profile.collision_box[2] / 2.0
    return out


@dataclass(frozen=True)
class _Setup:
    """What every step of one rollout reads: the policies' slots, the race line, the constants."""
    groups: list               # (entrant, iw, idr, tw, td) per entrant with slots: worlds and drones (numpy, torch)
    rules: set                 # opponent rules in use (more than two drones)
    opponent_rule: str         # for policies without their own
    gates: torch.Tensor        # (G, 3) m
    cum: torch.Tensor          # race line (cfrace.contract.observations.polyline)
    lap_len: torch.Tensor
    start_gate: torch.Tensor   # (W,) int64
    parked: torch.Tensor       # (W, 3) m, the opponent of a policy flying alone
    off_thrust: float          # N, motors off
    profile: DroneProfile
    rec_ids: torch.Tensor      # (K,) recorded worlds
    touch: float               # m, drone-drone contact distance
    eye: torch.Tensor          # (D, D) bool, a drone with itself
    flight: bool               # an entrant trained on the flight stack's path (metadata flight_obs): each
                               # step is flown in two halves for the 10 ms pose difference it observes
    min_thrust: float          # N, the firmware's least non-zero command (the floor of flight_obs entrants)


def _setup(track: Track, profile: DroneProfile, sim: Simulator, entrants: list[Entrant], assign: np.ndarray,
           starts: Starts, record: tuple[int, ...], opponent_rule: str) -> _Setup:
    """The rollout's fixed inputs: each entrant's slots, the race line, motors-off thrust, contact distance."""
    groups = []
    for p, e in enumerate(entrants):
        iw, idr = np.nonzero(assign == p)
        if iw.size == 0:
            continue
        groups.append((e, iw, idr, torch.as_tensor(iw), torch.as_tensor(idr)))
    d = assign.shape[1]
    rules = {e.meta.get("opponent_rule", opponent_rule) for e, *_ in groups if e.layout.opponent} if d > 2 else set()
    gates = torch.as_tensor(track.gate_array(), dtype=torch.float32)
    cum, lap_len = polyline(gates)
    off_thrust, _ = action_to_command(np.asarray(OFF_ACTION, np.float32), profile.mass, profile.max_thrust_weights,
                                      profile.max_rates_deg)
    return _Setup(groups, rules, opponent_rule, gates, cum, lap_len, starts.target[:, 0].to(torch.int64),
                  parked_opponents(track, profile, starts), off_thrust, profile, torch.as_tensor(record, dtype=torch.int64),
                  2.0 * (sim.radius + CONTACT_MARGIN), torch.eye(d, dtype=torch.bool),
                  any(bool(e.meta.get("flight_obs")) for e, *_ in groups),
                  float(profile.thrust_curve.to_newtons(FIRMWARE_MIN_THRUST_COUNTS)))


def _new_recording(n_steps: int, w: int, d: int, record: tuple[int, ...], laps: int) -> Recording:
    shape = (n_steps, w, d)
    return Recording(np.zeros(0), np.zeros(shape, bool), np.zeros(shape, np.float32),
                     np.full(shape, np.nan, np.float32), np.zeros(shape, bool), np.zeros(shape, bool),
                     np.zeros(shape, np.int8), np.zeros(shape, bool), np.zeros((n_steps, len(record), d, 3), np.float32),
                     tuple(record), np.zeros((w, d), np.int64), laps,
                     track_pos=np.zeros((n_steps, len(record), d), np.float32),
                     pair_contacts=np.zeros((w, d, d), np.int64), crash_partner=np.full((w, d), -1, np.int64))


def _commands(f: _Setup, sim: Simulator, nan_actions: np.ndarray, mid_pos: torch.Tensor | None = None,
              last_acc: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every slot's command for the next step: thrust (W, D) N, body rates (W, D, 3) deg/s and the
    collective acceleration it asks (W, D) m/s^2 (before the thrust floor); one onnxruntime call per
    policy for all its slots; non-finite actions become motors off (counted in ``nan_actions`` (W, D)).
    An entrant trained on the flight stack's path (metadata flight_obs) sees velocities as the pose
    difference since ``mid_pos`` (10 ms ago) and its thrust floored at the firmware's least non-zero
    command, as RaceEnv gave them in its training; one trained through the lab loop (metadata loop)
    sees that difference brought to the pose's time by the last command ``last_acc``, as the loop at
    zero latency and the flight stack's estimator give it (cfrace.loopmodel.predict_commanded)."""
    w, d = sim.pos.shape[:2]
    off = np.asarray(OFF_ACTION, np.float32)
    thrust = np.full((w, d), f.off_thrust, np.float32)
    acc = np.full((w, d), f.off_thrust / f.profile.mass, np.float32)
    rates = np.zeros((w, d, 3), np.float32)
    pos, rot, target = sim.pos, sim.rot(), sim.race.target
    vel_exact = sim.vel
    vel_flight = (pos - mid_pos) / MOCAP_DT if mid_pos is not None else vel_exact
    vel_loop = vel_flight
    if last_acc is not None and mid_pos is not None and any(e.meta.get("loop") for e, *_ in f.groups):
        _, vel_loop = predict_commanded(pos, vel_flight, sim.quat, last_acc.unsqueeze(-1), 0.0, MOCAP_DT / 2)
    tpos = track_position(f.gates, f.cum, f.lap_len, f.start_gate, sim.race.gates_passed, target, pos)
    opp = {rule: choose_opponents(pos, tpos, ~sim.race.crashed, rule) for rule in f.rules}
    for e, iw, idr, tw, td in f.groups:
        flight = bool(e.meta.get("flight_obs"))
        vel = (vel_loop if e.meta.get("loop") else vel_flight) if flight else vel_exact
        opp_pos = opp_vel = None
        if e.layout.opponent:
            if d > 2:
                oi = opp[e.meta.get("opponent_rule", f.opponent_rule)][tw, td]
                opp_pos, opp_vel = pos[tw, oi], vel[tw, oi]
            elif d == 2:
                opp_pos, opp_vel = pos[tw, 1 - td], vel[tw, 1 - td]
            else:
                opp_pos, opp_vel = f.parked[tw], torch.zeros(iw.shape[0], 3)
        obs = build_observation(pos[tw, td], vel[tw, td], rot[tw, td], target[tw, td], sim.gate_corners,
                                e.layout, opp_pos, opp_vel)
        act = e.policy(obs.numpy())                      # one onnxruntime call for all its slots
        bad = ~np.isfinite(act).all(-1)
        if bad.any():
            act[bad] = off
            np.add.at(nan_actions, (iw[bad], idr[bad]), 1)
        th, rt = action_to_command(act, f.profile.mass, e.meta["max_thrust_weights"], e.meta["max_rates_deg"])
        acc[iw, idr] = th / f.profile.mass
        if flight:   # motors off (a non-finite action) stays off
            th = np.where(bad, th, np.maximum(th, f.min_thrust))
        thrust[iw, idr], rates[iw, idr] = th, rt
    return torch.from_numpy(thrust), torch.from_numpy(rates), torch.from_numpy(acc)


def _record(r: Recording, step: int, f: _Setup, sim: Simulator, ev, active: torch.Tensor,
            prev_pairs: torch.Tensor) -> torch.Tensor:
    """Write step ``step``'s figures into ``r`` (``ev``: the simulator's events of the step, ``active``
    (W, D): racing during it); returns the drone pairs in contact (W, D, D) for the next step."""
    race = sim.race
    lap_now = (ev.laps > 0) & active
    r.active[step] = active.numpy()
    r.speed[step] = torch.linalg.vector_norm(sim.vel, dim=-1).numpy()
    r.lap_stamp[step] = torch.where(lap_now, race.lap_start, float("nan")).numpy()
    r.contact[step] = ev.contact.numpy()
    r.crashed_now[step] = ev.crashed_now.numpy()
    r.reason[step] = ev.reason.numpy().astype(np.int8)
    r.crashed[step] = race.crashed.numpy()
    if sim.pos.shape[1] > 1:  # drone-drone contacts by pair: within contact distance at the step's end, both racing
        dist = torch.cdist(sim.pos, sim.pos)
        pairs = (dist < f.touch) & ev.contact.unsqueeze(-1) & ev.contact.unsqueeze(-2) & ~f.eye
        racing = active.unsqueeze(-1) & active.unsqueeze(-2)
        r.pair_contacts += (pairs & ~prev_pairs & racing).numpy()
        partner = torch.where(pairs, dist, torch.inf).argmin(-1)
        hit = ev.crashed_now & active & pairs.any(-1)
        r.crash_partner[hit.numpy()] = partner[hit].numpy()
        prev_pairs = pairs
    if len(f.rec_ids):
        r.pos[step] = sim.pos[f.rec_ids].numpy()
        r.track_pos[step] = track_position(f.gates, f.cum, f.lap_len, f.start_gate, race.gates_passed, race.target,
                                           sim.pos)[f.rec_ids].numpy()
    return prev_pairs


def rollout(track: Track, profile: DroneProfile, obstacles: bool, entrants: list[Entrant], assign: np.ndarray,
            starts: Starts, laps: int, time_limit_s: float | None = None, record: tuple[int, ...] = (),
            seed: int = 0, threads: int | None = None, until_all: bool = False,
            opponent_rule: str = DEFAULT_OPPONENT_RULE) -> Recording:
    """Fly every world to the end; ``assign`` (W, D) int: entrant index per slot, -1 = motors off.
    ``opponent_rule``: who a policy without its own ``opponent_rule`` metadata observes when there
    are more than two drones (cfrace.contract.observations.choose_opponents)."""
    assign = np.asarray(assign, dtype=np.int64)
    w, d = assign.shape
    limit = laps * LAP_TIME_LIMIT_S if time_limit_s is None else time_limit_s
    n_steps = int(math.ceil(limit / POLICY_DT - 1e-9))
    # one simulator thread by default: on a shared 2-core machine OpenMP threads mostly wait on each other
    sim = Simulator(track, profile, w, d, obstacles=obstacles, seed=seed, threads=threads or 1)
    sim.reset(torch.arange(w), starts.pos, quat=starts.quat, target=starts.target)
    f = _setup(track, profile, sim, entrants, assign, starts, record, opponent_rule)
    r = _new_recording(n_steps, w, d, record, laps)
    prev_pairs = torch.zeros(w, d, d, dtype=torch.bool)
    finished = torch.zeros(w, d, dtype=torch.bool)
    over = torch.zeros(w, dtype=torch.bool)
    mid_pos = sim.pos.clone() if f.flight else None   # the pose 10 ms before the step's end (flight_obs)
    last_acc = None                                   # the last command's collective acceleration (loop)
    t0 = time.perf_counter()
    step = 0
    with torch.no_grad():
        for step in range(n_steps):
            active = ~sim.race.crashed & ~finished & ~over.unsqueeze(-1)
            *cmd, last_acc = _commands(f, sim, r.nan_actions, mid_pos, last_acc)
            if f.flight:   # RaceEnv.step's two halves
                first = sim.step(*cmd, SUBSTEPS // 2)
                mid_pos = sim.pos.clone()
                ev = first.then(sim.step(*cmd, SUBSTEPS - SUBSTEPS // 2))
            else:
                ev = sim.step(*cmd, SUBSTEPS)
            prev_pairs = _record(r, step, f, sim, ev, active, prev_pairs)
            race = sim.race
            finished |= (race.laps >= laps) & active
            over |= (race.crashed | finished).all(-1) if until_all else finished.any(-1) | (race.crashed | finished).all(-1)
            if bool(over.all()):
                break
    n = step + 1
    r.gates_passed = sim.race.gates_passed.numpy().copy()
    for name in ("active", "speed", "lap_stamp", "contact", "crashed_now", "reason", "crashed", "pos", "track_pos"):
        setattr(r, name, getattr(r, name)[:n])
    r.t = (np.arange(n) + 1) * POLICY_DT
    r.wall_s = time.perf_counter() - t0
    return r
