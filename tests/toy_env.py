"""A tiny batched multi-agent task with RaceEnv's interface, for fast RL tests and benchmarks.

Each agent is a point in the plane that must reach its goal (dense progress reward + a bonus per
goal, then a new goal). Leaving the box |p| <= 3 is a crash: the agent terminates, stays dead
(alive = False, reward 0) until every agent of the world is done, then the world auto-resets.
The time limit truncates. So it exercises everything the runner must get right: terminated vs
truncated, dead steps, auto-reset with ``final_critic``, named reward terms and episode stats.
It learns within seconds, which makes "training improves the return" a fast test.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch


@dataclass
class StepResult:
    obs: torch.Tensor           # (E, A, obs_dim) next observations (after auto-reset)
    critic: torch.Tensor        # (E, A, critic_dim)
    reward: torch.Tensor        # (E, A)
    terminated: torch.Tensor    # (E, A) bool
    truncated: torch.Tensor     # (E, A) bool
    alive: torch.Tensor         # (E, A) bool, the agent acted in this step
    final_critic: torch.Tensor  # (E, A, critic_dim) critic obs of the state reached, before reset
    terms: dict = field(default_factory=dict)   # name -> (E, A)
    stats: dict = field(default_factory=dict)   # name -> float


class ToyRaceEnv:
    DT = 0.1        #: s per step
    BOX = 1.5       #: m, crash when |x| or |y| exceeds it
    GOAL_R = 0.3    #: m, goal radius

    def __init__(self, num_envs: int, num_agents: int = 2, *, episode_steps: int = 40, device="cpu", seed: int = 0,
                 randomize: bool = True, layout: str | None = None):
        """layout: a name from LAYOUTS to pad the observation to that layout's size (noise
        features), so that checkpoints of the toy env can be exported like real ones."""
        from cfrace.contract.observations import LAYOUTS

        self.num_envs, self.num_agents, self.episode_steps = num_envs, num_agents, episode_steps
        self.device = torch.device(device)
        self.core_dim = 6 + (2 if num_agents > 1 else 0)
        self.layout = LAYOUTS[layout] if layout is not None else None
        self.obs_dim = self.layout.dim if self.layout is not None else self.core_dim
        self.critic_dim = self.obs_dim * num_agents
        self.randomize = randomize
        self.gen = torch.Generator(device=self.device).manual_seed(seed)
        e, a = num_envs, num_agents
        z = lambda *s: torch.zeros(*s, device=self.device)  # noqa: E731
        self.p, self.v, self.goal = z(e, a, 2), z(e, a, 2), z(e, a, 2)          # (E, A, 2)
        self.t = torch.zeros(e, dtype=torch.long, device=self.device)           # (E,) steps
        self.alive = torch.ones(e, a, dtype=torch.bool, device=self.device)     # (E, A)
        self.goals = z(e, a)                                                    # (E, A) reached

    def _rand(self, *shape) -> torch.Tensor:
        return torch.rand(*shape, generator=self.gen, device=self.device)

    def _reset_worlds(self, ids: torch.Tensor) -> None:
        n = len(ids)
        self.p[ids] = (self._rand(n, self.num_agents, 2) - 0.5) * 2.0
        self.v[ids] = 0.0
        self.goal[ids] = (self._rand(n, self.num_agents, 2) - 0.5) * 2.4
        self.t[ids] = 0
        self.alive[ids] = True
        self.goals[ids] = 0.0

    def _observe(self) -> tuple[torch.Tensor, torch.Tensor]:
        own = torch.cat([self.goal - self.p, self.v, self.p], -1)                # (E, A, 6)
        if self.num_agents > 1:
            own = torch.cat([own, self.p.flip(1) - self.p], -1)
        if self.obs_dim > self.core_dim:  # padding features: noise with distinct offsets and scales
            pad = self.obs_dim - self.core_dim
            k = torch.arange(pad, device=self.device, dtype=torch.float32)
            noise = torch.randn(self.num_envs, self.num_agents, pad, generator=self.gen, device=self.device)
            own = torch.cat([own, noise * (0.1 + 0.2 * k) + k - pad / 2], -1)
        if self.num_agents > 1:
            critic = torch.cat([own.roll(-k, 1) for k in range(self.num_agents)], -1)  # own, then the others
        else:
            critic = own.clone()
        return own, critic

    def reset(self) -> tuple[torch.Tensor, torch.Tensor]:
        self._reset_worlds(torch.arange(self.num_envs, device=self.device))
        if self.randomize:  # spread episode ends over time, like RaceEnv does
            self.t[:] = (self._rand(self.num_envs) * self.episode_steps).long()
        return self._observe()

    def step(self, actions: torch.Tensor) -> StepResult:
        a = actions.clamp(-1, 1)
        alive = self.alive.clone()
        live = alive.float().unsqueeze(-1)
        d0 = (self.goal - self.p).norm(dim=-1)
        self.v = self.v + live * (4.0 * a[..., :2] - 0.5 * self.v) * self.DT
        self.p = self.p + live * self.v * self.DT
        d1 = (self.goal - self.p).norm(dim=-1)
        reached = alive & (d1 < self.GOAL_R)
        crashed = alive & (self.p.abs() > self.BOX).any(-1)
        self.goals += reached.float()
        new_goal = (self._rand(self.num_envs, self.num_agents, 2) - 0.5) * 2.4
        self.goal = torch.where(reached.unsqueeze(-1), new_goal, self.goal)
        self.t += 1
        terms = {"progress": torch.where(alive, d0 - d1, 0.0), "goal": reached.float(),
                 "crash": -crashed.float(), "cmd": torch.where(alive, -0.01 * a[..., 2:].square().sum(-1), 0.0)}
        reward = sum(terms.values())
        terminated = crashed
        timeout = (self.t >= self.episode_steps).unsqueeze(-1) & alive & ~crashed
        self.alive = alive & ~crashed & ~timeout
        obs, critic = self._observe()
        final_critic = critic.clone()
        world_done = ~self.alive.any(-1)
        stats = {}
        ids = world_done.nonzero().squeeze(-1)
        if len(ids):
            secs = self.t[ids].float().clamp(min=1) * self.DT
            stats = {"gates_per_s": float((self.goals[ids] / secs.unsqueeze(-1)).mean()),
                     "success": float((~(self.p[ids].abs() > self.BOX).any(-1)).float().mean())}
            self._reset_worlds(ids)
            obs, critic = self._observe()
        return StepResult(obs, critic, reward, terminated, timeout, alive, final_critic, terms, stats)

    def state_dict(self) -> dict:
        return {"p": self.p.clone(), "v": self.v.clone(), "goal": self.goal.clone(), "t": self.t.clone(),
                "alive": self.alive.clone(), "goals": self.goals.clone(), "gen": self.gen.get_state()}

    def load_state_dict(self, state: dict) -> None:
        for k in ("p", "v", "goal", "t", "alive", "goals"):
            setattr(self, k, state[k].to(self.device).clone())
        self.gen.set_state(state["gen"])
