"""Batched race environment over the simulator: E worlds, A agents (multi-agent: 2 by default, or
N drones per world with ``drones``; single-agent: 1).

Hooks in a fixed order per step: apply actions (action map) -> simulate 10 x 2 ms -> race
bookkeeping -> reward terms -> dones -> observe -> auto-reset finished worlds.
Terminated (crash) and truncated (time-out) stay apart; a crashed drone stays out (frozen, alive =
False) until its world resets, which happens once every drone of the world is done.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from cfrace.contract import MULTI_AGENT_METHODS, POLICY_DT
from cfrace.drone import DroneProfile
from cfrace.contract.actions import FIRMWARE_MIN_THRUST_COUNTS, action_to_command
from cfrace.contract.observations import (DEFAULT_OPPONENT_RULE, OPPONENT_RULES, build_observations, choose_opponents,
                                     critic_observations, layout_for, polyline, track_position)
from cfrace.env.rewards import MULTI_AGENT, RewardInputs, RewardScales, leading, overtaking, reward_terms
from cfrace.errors import ConfigError
from cfrace.env.labloop import MOCAP_DT, LabLoop
from cfrace.loopmodel import DroneRanges, LoopRanges
from cfrace.sim.dynamics import quat_to_rot
from cfrace.sim.simulator import CrashRules, Simulator
from cfrace.track import HEADING_JITTER_RAD, Track, start_grid

SPAWN_REDRAWS = 50   #: draws of the starts that left the arena before giving up (cfrace.env.RaceEnv.spawn)

SUBSTEPS = 10
assert SUBSTEPS // 2 * Simulator.dt == MOCAP_DT   # the mid-step pose sample is one 100 Hz mocap frame back


@dataclass
class StepResult:
    obs: torch.Tensor           # (E, A, obs_dim) next observation (after auto-reset)
    critic: torch.Tensor        # (E, A, critic_dim)
    reward: torch.Tensor        # (E, A)
    terminated: torch.Tensor    # (E, A) bool, crashed in this step
    truncated: torch.Tensor     # (E, A) bool, time-out in this step (alive agents)
    alive: torch.Tensor         # (E, A) bool, the agent acted in this step
    final_critic: torch.Tensor  # (E, A, critic_dim) critic obs of the reached state (before reset)
    terms: dict[str, torch.Tensor]
    stats: dict[str, float] = field(default_factory=dict)


def parked_share(method: str, frac: float) -> float:
    """RaceEnv's ``parked_frac`` (`cfrace train --parked-opponent-frac`), checked (ConfigError, one
    line): the share of the races whose last drone starts crashed, at rest on the floor below its start
    slot (what a policy flying alone sees of its stopped opponent in the flight stack's dry-run and in
    cfrace.evaluate.rollout.parked_opponents): the others race nobody."""
    if not 0.0 <= frac < 1.0:
        raise ConfigError(f"--parked-opponent-frac must be in [0, 1), got {frac}")
    if frac > 0 and not MULTI_AGENT[method]:
        raise ConfigError(f"--parked-opponent-frac needs a multi-agent method "
                          f"({', '.join(MULTI_AGENT_METHODS)}), not {method}")
    return float(frac)


class RaceEnv(LabLoop):
    def __init__(self, track: Track, profile: DroneProfile, *, num_envs: int, method: str, obstacles: bool,
                 device: str | torch.device = "cpu", seed: int = 0, randomize: bool = True, episode_s: float = 30.0,
                 compile: bool = False, start: str = "mixed", rewards: RewardScales = RewardScales(),
                 rules: CrashRules = CrashRules(), random_phase: bool = False, flight_obs: bool = False,
                 drones: int | None = None, opponent_rule: str = DEFAULT_OPPONENT_RULE,
                 loop: LoopRanges | None = None, drone: DroneRanges | None = None, parked_frac: float = 0.0):
        if method not in MULTI_AGENT:
            raise ValueError(f"unknown method {method!r}")
        if drones is not None and (drones < 2 or not MULTI_AGENT[method]):
            raise ValueError(f"drones: at least 2, and only for the multi-agent methods (got {drones} for {method})")
        if opponent_rule not in OPPONENT_RULES:
            raise ValueError(f"unknown opponent rule {opponent_rule!r} (choose from {', '.join(OPPONENT_RULES)})")
        self.track, self.profile, self.method = track, profile, method
        self.obstacles = obstacles and bool(track.obstacles)
        self.num_envs = num_envs
        self.num_agents = (drones or 2) if MULTI_AGENT[method] else 1
        self.opponent_rule = opponent_rule   #: which drone each one observes when N > 2 (observations.py)
        self.device = torch.device(device)
        self.randomize, self.start_mode, self.scales = randomize, start, rewards
        self.random_phase = random_phase   #: reset(): first races get a random share of the time limit
        self.obstacle_curriculum = False   #: set_obstacle_scale was called (the size is then logged)
        # flight_obs: the observation and command path of the flight stack (docs/training.md, "Flight
        # observations"): velocity = the last 10 ms pose difference, as the flight loop's estimator
        # computes it from 100 Hz mocap; thrust at least the firmware's least non-zero command
        # loop: the lab's loop (cfrace.loopmodel): delayed, noisy, dropped mocap frames read through the
        # flight estimator's rules, late setpoints; implies flight_obs. drone: drone-model randomisation
        # (replaces the paper's ranges)
        self.loop, self.drone = loop, drone
        self.parked_frac = parked_share(method, parked_frac)
        self.flight_obs = bool(flight_obs) or loop is not None
        self.min_thrust_n = float(profile.thrust_curve.to_newtons(FIRMWARE_MIN_THRUST_COUNTS))
        self.max_steps = int(round(episode_s / POLICY_DT))
        self.sim = Simulator(track, profile, num_envs, self.num_agents, obstacles=self.obstacles, device=self.device,
                             seed=seed, compile=compile, rules=rules)
        self.layout = layout_for(self.num_agents >= 2, self.obstacles)
        self.obs_dim = self.layout.dim
        self.critic_dim = self.obs_dim * self.num_agents
        self.gen = torch.Generator(device="cpu").manual_seed(seed)
        g = track.gate_array()
        self.gates = torch.as_tensor(g, dtype=torch.float32, device=self.device)           # (G, 4)
        self.cum, self.lap_len = polyline(self.gates)     # m to gate g from gate 0, m per lap
        e, a, dev = num_envs, self.num_agents, self.device
        self.steps = torch.zeros(e, dtype=torch.int64, device=dev)
        self.start_gate = torch.zeros(e, dtype=torch.int64, device=dev)
        self.laps_paid = torch.zeros(e, dtype=torch.int64, device=dev)
        self.prev_pos = torch.zeros(e, a, 3, device=dev)
        self.mid_pos = torch.zeros(e, a, 3, device=dev)   #: positions 10 ms before the step's end (flight_obs)
        self.prev_track_pos = torch.zeros(e, a, device=dev)
        self.ep_return = torch.zeros(e, a, device=dev)
        self.ep_lead = torch.zeros(e, a, device=dev)
        self.ep_first_lap = torch.full((e, a), -1.0, device=dev)
        self.parked = torch.zeros(e, a, dtype=torch.bool, device=dev)   #: drones parked at their world's reset
        self._stats: dict[str, list] = {}
        self._extra: tuple[str, ...] = ()
        self._init_lab(e, a, dev)

    # ------------------------------------------------------------------ helpers
    def set_obstacle_scale(self, scale: float) -> None:
        """The obstacle curriculum: the obstacles at ``scale`` of their size (Simulator.set_obstacle_scale)."""
        if not self.obstacles:
            raise ConfigError("--obstacle-curriculum: this race has no obstacles (needs --obstacles and a track "
                              "with obstacles)")
        self.sim.set_obstacle_scale(scale)
        self.obstacle_curriculum = True   # from now on the episode figures say the size (stat_obstacle_scale)

    def _rand(self, *shape) -> torch.Tensor:
        return torch.rand(*shape, generator=self.gen).to(self.device)

    def _randn(self, *shape) -> torch.Tensor:
        return torch.randn(*shape, generator=self.gen).to(self.device)

    def track_position(self) -> torch.Tensor:
        """(E, A) m flown along the gate polyline since the start gate (p of the overtaking term)."""
        r = self.sim.race
        return track_position(self.gates, self.cum, self.lap_len, self.start_gate, r.gates_passed, r.target,
                              self.sim.pos)

    def dist_to_target(self, pos: torch.Tensor | None = None) -> torch.Tensor:
        pos = self.sim.pos if pos is None else pos
        return torch.linalg.vector_norm(pos - self.gates[self.sim.race.target][..., :3], dim=-1)

    def observe(self) -> tuple[torch.Tensor, torch.Tensor]:
        s = self.sim
        if self.loop is not None:
            pos, vel, quat = self._loop_observe()
            rot = quat_to_rot(quat)
        else:
            pos, rot = s.pos, s.rot()
            vel = (s.pos - self.mid_pos) / MOCAP_DT if self.flight_obs else s.vel
        if self.num_agents > 2:
            opp = choose_opponents(pos, self.track_position(), ~s.race.crashed, self.opponent_rule)
            obs = build_observations(pos, vel, rot, s.race.target, s.gate_corners, self.layout, opp)
            return obs, critic_observations(obs, opp)
        obs = build_observations(pos, vel, rot, s.race.target, s.gate_corners, self.layout)
        critic = critic_observations(obs) if self.num_agents == 2 else obs
        return obs, critic

    # ------------------------------------------------------------------ reset
    def reset(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Reset every world. With ``random_phase`` each world's first race starts with a random
        number of its steps already used (its first time-out comes early), so that the worlds'
        races are spread over every phase from the first rollout on instead of all starting and
        timing out together."""
        self._reset_worlds(torch.arange(self.num_envs, device=self.device))
        if self.random_phase:
            self.steps = torch.randint(0, self.max_steps, (self.num_envs,), generator=self.gen).to(self.device)
        return self.observe()

    def spawn(self, n: int):
        """Start poses for n worlds: a random gate start (before a gate, on its +n side) or a ground
        start before gate 0. Drones side by side (track spawn ``opponent_offset``), one of them
        ``opponent_stagger`` m further back (which one is random). More drones: the track's start
        grid (cfrace.track.start_grid), each drone in a random slot; a start that puts a slot
        outside the arena (a deep grid before a gate near a wall) is drawn again.
        Returns pos (n, A, 3), quat (n, A, 4), target (n,)."""
        pos, quat, gate_idx = self._draw_starts(n)
        for draw in range(SPAWN_REDRAWS + 1 if self.num_agents > 2 else 0):
            out = torch.as_tensor(self.track.arena.outside_xy(pos.cpu().numpy())).any(-1)
            if not out.any():
                break
            if draw == SPAWN_REDRAWS:
                raise ConfigError(f"the {self.num_agents}-drone start grid of the {self.track.name} track leaves its "
                                  f"arena in {SPAWN_REDRAWS} draws in a row: fewer drones, or gate starts")
            ids = torch.nonzero(out).squeeze(-1)
            pos[ids], quat[ids], gate_idx[ids] = self._draw_starts(len(ids))
        return pos, quat, gate_idx

    def _draw_starts(self, n: int):
        """One draw of ``spawn``'s start poses, some maybe outside the arena."""
        sp, a, g = self.track.spawn, self.num_agents, self.gates.shape[0]
        if self.start_mode == "ground":
            ground = torch.ones(n, dtype=torch.bool)
        elif self.start_mode == "gate":
            ground = torch.zeros(n, dtype=torch.bool)
        else:
            ground = torch.rand(n, generator=self.gen) < sp.ground_start_prob
        gate_idx = torch.randint(0, g, (n,), generator=self.gen)
        gate_idx = torch.where(ground, torch.zeros_like(gate_idx), gate_idx).to(self.device)
        gate = self.gates[gate_idx]                                                  # (n, 4)
        yaw = gate[:, 3]
        normal = torch.stack([torch.cos(yaw), torch.sin(yaw), torch.zeros_like(yaw)], -1)
        side = torch.stack([-torch.sin(yaw), torch.cos(yaw), torch.zeros_like(yaw)], -1)
        lo, hi = sp.gate_distance
        ground_d = self.device
        dist = torch.where(ground.to(ground_d), torch.full((n,), sp.ground_distance, device=ground_d),
                           lo + (hi - lo) * self._rand(n))
        jitter = (self._rand(n, 2) * 2 - 1) * sp.lateral
        centre = gate[:, :3] + normal * dist.unsqueeze(-1) + side * jitter[:, :1]
        centre[:, 2] = centre[:, 2] + jitter[:, 1]
        if a == 2:
            half = torch.tensor([-0.5, 0.5], device=self.device)
            swap = (self._rand(n) < 0.5).unsqueeze(-1)
            offs = torch.where(swap, half.flip(0), half) * sp.opponent_offset         # (n, 2) m sideways
            back = (torch.where(swap, half.flip(0), half) + 0.5) * sp.opponent_stagger  # (n, 2) m along +n: 0 or stagger
            pos = centre.unsqueeze(1) + side.unsqueeze(1) * offs.unsqueeze(-1) + normal.unsqueeze(1) * back.unsqueeze(-1)
        elif a > 2:
            grid = torch.as_tensor(start_grid(sp, self.track.gate, a), dtype=torch.float32, device=self.device)
            slot = torch.rand(n, a, generator=self.gen).argsort(-1).to(self.device)     # drone -> slot
            offs, back = grid[slot, 0], grid[slot, 1]                                    # (n, A) m
            pos = centre.unsqueeze(1) + side.unsqueeze(1) * offs.unsqueeze(-1) + normal.unsqueeze(1) * back.unsqueeze(-1)
        else:
            pos = centre.unsqueeze(1)
        z_rest = self.sim.z_rest
        pos[..., 2] = torch.where(ground.to(self.device).unsqueeze(-1), torch.full_like(pos[..., 2], z_rest),
                                  pos[..., 2].clamp_min(0.3))
        heading = yaw + math.pi + (self._rand(n) * 2 - 1) * HEADING_JITTER_RAD    # face along -n
        half = (heading / 2).unsqueeze(-1).expand(n, a)
        quat = torch.stack([torch.cos(half), torch.zeros_like(half), torch.zeros_like(half), torch.sin(half)], -1)
        return pos, quat, gate_idx

    def _reset_worlds(self, ids: torch.Tensor) -> None:
        n, a = ids.shape[0], self.num_agents
        if n == 0:
            return
        pos, quat, gate_idx = self.spawn(n)
        parked = torch.zeros(n, a, dtype=torch.bool, device=self.device)
        if self.parked_frac > 0:   # no draw otherwise: runs without parked opponents keep their random stream
            parked[:, -1] = self._rand(n) < self.parked_frac
            pos[..., 2] = torch.where(parked, torch.full_like(pos[..., 2], self.sim.z_rest), pos[..., 2])
        self.sim.reset(ids, pos, quat=quat, target=gate_idx.unsqueeze(-1).expand(n, a))
        self.sim.race.crashed[ids] = parked
        self.parked[ids] = parked
        u = lambda lo, hi, *shape: (lo + (hi - lo) * self._rand(n, a, *shape))
        if self.drone is not None:
            self._reset_drone(ids, u)
        elif self.randomize:
            scales = dict(k_aero=u(0.5, 2.0, 3), kp=u(0.85, 1.15, 1).expand(n, a, 3),
                          ki=u(0.85, 1.15, 1).expand(n, a, 3), kd=u(0.7, 1.2, 1).expand(n, a, 3))
            if a == 1:
                scales["tau_m"] = u(0.2, 2.0, 1)
            self.sim.set_scales(ids, **scales)
        if self.loop is not None:
            self._reset_loop(ids, u)
        self.steps[ids] = 0
        self.start_gate[ids] = gate_idx
        self.laps_paid[ids] = 0
        self.prev_pos[ids] = self.sim.pos[ids]
        self.mid_pos[ids] = self.sim.pos[ids]
        self.prev_track_pos[ids] = self.track_position()[ids]
        self.ep_return[ids] = 0.0
        self.ep_lead[ids] = 0.0
        self.ep_first_lap[ids] = -1.0

    # ------------------------------------------------------------------ step
    def step(self, actions: torch.Tensor) -> StepResult:
        sim = self.sim
        actions = actions.to(self.device).clamp(-1.0, 1.0)
        alive = ~sim.race.crashed.clone()
        thrust, rates = action_to_command(actions, self.profile.mass, self.profile.max_thrust_weights,
                                          self.profile.max_rates_deg)
        laps_before = sim.race.laps.clone()
        acc = thrust / self.profile.mass if self.loop is not None else None   # the loop prediction's command
        if self.flight_obs:
            thrust = thrust.clamp_min(self.min_thrust_n)
        if self.drone is not None:   # the thrust this drone delivers for the command
            thrust = self._delivered(thrust)
        if self.flight_obs:
            half = SUBSTEPS // 2
            e1 = self._late_first_half(thrust, rates, half, acc) if self.loop is not None else sim.step(thrust, rates, half)
            self.mid_pos = sim.pos.clone()
            e2 = sim.step(thrust, rates, SUBSTEPS - half)
            if self.loop is not None:
                self._push_pose()
            ev = e1.then(e2)
        else:
            ev = sim.step(thrust, rates, SUBSTEPS)
        self.steps += 1
        # race bookkeeping: progress, leader, lap bonus once per lap per race
        d_now = self.dist_to_target()
        d_prev = self.dist_to_target(self.prev_pos)
        progress = torch.where(alive & ~ev.crashed_now, d_prev - d_now, torch.zeros_like(d_now))
        now_alive = ~sim.race.crashed
        lead = leading(sim.race.gates_passed, d_now, now_alive)
        lap_done = sim.race.laps > laps_before
        new_lap = lap_done & (sim.race.laps > self.laps_paid.unsqueeze(-1)) & lead
        self.laps_paid = torch.maximum(self.laps_paid, torch.where(new_lap, sim.race.laps, 0).amax(-1))
        track_pos = self.track_position()
        ot = overtaking(track_pos, self.prev_track_pos) if self.num_agents >= 2 else torch.zeros_like(progress)
        ot = torch.where(alive, ot, torch.zeros_like(ot))
        terms = reward_terms(self.method, RewardInputs(actions, ev.gates, new_lap, lead, ev.contact, ev.crashed_now,
                                                       progress, ot, POLICY_DT), self.scales)
        terms = {k: torch.where(alive, v, torch.zeros_like(v)) for k, v in terms.items()}
        reward = sum(terms.values())
        self.prev_pos = sim.pos.clone()
        self.prev_track_pos = track_pos
        # dones
        terminated = ev.crashed_now & alive
        timeout = (self.steps >= self.max_steps).unsqueeze(-1)
        truncated = timeout & alive & ~terminated
        obs_final, critic_final = self.observe()
        world_done = timeout.squeeze(-1) | sim.race.crashed.all(-1)
        # episode statistics
        self.ep_return += reward
        self.ep_lead += (lead & now_alive).float()
        first = lap_done & (self.ep_first_lap < 0)
        self.ep_first_lap = torch.where(first, self.steps.unsqueeze(-1).float() * POLICY_DT, self.ep_first_lap)
        stats = self._collect_stats(world_done)
        done_ids = world_done.nonzero().squeeze(-1)
        self._reset_worlds(done_ids)
        obs, critic = self.observe() if done_ids.numel() else (obs_final, critic_final)
        return StepResult(obs, critic, reward, terminated, truncated, alive, critic_final, terms, stats)

    # ------------------------------------------------------------------ checkpoints (exact resume)
    _COUNTERS = ("steps", "start_gate", "laps_paid", "prev_pos", "prev_track_pos", "ep_return", "ep_lead",
                 "ep_first_lap", "mid_pos", "parked")

    def state_dict(self) -> dict:
        s = self.sim
        return {"drone": [t.clone() for t in s.state], "race": [t.clone() for t in s.race],
                "scales": {k: v.clone() for k, v in s.scales.items()},
                "counters": {k: getattr(self, k).clone() for k in self._COUNTERS + self._extra},
                "gen": self.gen.get_state(), "sim_gen": s.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        s = self.sim
        for dst, src in zip(s.state, state["drone"]):
            dst.copy_(src)
        for dst, src in zip(s.race, state["race"]):
            dst.copy_(src)
        for k, v in state["scales"].items():
            s.scales[k].copy_(v)
        s._update_params()
        for k, v in state["counters"].items():
            setattr(self, k, v.clone().to(self.device))
        self.gen.set_state(state["gen"])
        s.generator.set_state(state["sim_gen"])

    def _collect_stats(self, done: torch.Tensor) -> dict[str, float]:
        if not bool(done.any()):
            return {}
        r, steps = self.sim.race, self.steps[done].float().clamp_min(1)
        out = {
            "episode_return": self.ep_return[done].mean().item(),
            "gates_per_s": (r.gates_passed[done].float() / (steps.unsqueeze(-1) * POLICY_DT)).mean().item(),
            "success": (r.laps[done] >= 1).float().mean().item(),
            "crash_rate": (r.crashed[done].float().mean().item() if not self.parked_frac else   # of those that flew
                           (r.crashed[done] & ~self.parked[done]).sum().item() / max(1, int((~self.parked[done]).sum()))),
            "episode_s": (steps * POLICY_DT).mean().item(),
        }
        if self.obstacle_curriculum:
            out["obstacle_scale"] = self.sim.obstacle_scale
        lap = r.lap_last[done]
        if bool((~lap.isnan()).any()):
            out["lap_time_s"] = lap[~lap.isnan()].mean().item()
        for i in range(self.num_agents):
            out[f"return_agent{i}"] = self.ep_return[done][:, i].mean().item()
        if self.num_agents >= 2:
            out["lead_share_agent0"] = (self.ep_lead[done][:, 0] / steps).mean().item()
            score = r.gates_passed[done].float() * 1000 - torch.nan_to_num(self.ep_first_lap[done], nan=0.0)
            out["win_share_agent0"] = (score[:, 0] > score[:, 1:].amax(-1)).float().mean().item()
        return out
