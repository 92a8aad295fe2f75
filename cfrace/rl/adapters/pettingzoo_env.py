"""PettingZoo ParallelEnv of the race: one world, every drone of the method an agent.

Agents are "drone_0" (the ego) and, for the multi-agent methods (ours, dm), "drone_1". A drone
that crashes is terminated and leaves `agents`; the other races on (RaceEnv keeps the crashed
drone frozen). At the time limit the drones still racing are truncated. When no agent is left
the episode is over: call reset() (passes pettingzoo.test.parallel_api_test).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from pettingzoo import ParallelEnv

from cfrace.rl.adapters import AGENT_PREFIX, final_observations, make_race_env, reseed, spaces


class _RaceAgents:
    """A RaceEnv of ``num_envs`` worlds whose drones are agents drone_0, drone_1 (same spaces,
    the same objects on every call)."""

    def _build(self, method: str, track: str, num_envs: int, obstacles: bool, seed: int, kw: dict) -> None:
        self.race, self.meta = make_race_env(method, track, num_envs, obstacles, seed, **kw)
        self.possible_agents = [f"{AGENT_PREFIX}{i}" for i in range(self.race.num_agents)]
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self._spaces = spaces(self.race)

    def observation_space(self, agent: str):
        return self._spaces[0]

    def action_space(self, agent: str):
        return self._spaces[1]


class RaceParallelEnv(_RaceAgents, ParallelEnv):
    metadata = {"name": "cfrace_race_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(self, method: str = "ours", track: str = "lemniscate", obstacles: bool = False, seed: int = 0,
                 **kw: Any):
        self._build(method, track, 1, obstacles, seed, kw)
        self.agents: list[str] = []

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            reseed(self.race, seed)
        obs, _ = self.race.reset()
        self.agents = self.possible_agents[:]
        return ({a: obs[0, i].numpy().copy() for a, i in self._index.items()},
                {a: {} for a in self.agents})

    def step(self, actions: dict[str, Any]):
        act = torch.zeros(1, self.race.num_agents, 4)
        for a, v in actions.items():
            act[0, self._index[a]] = torch.as_tensor(np.asarray(v, np.float32)).reshape(4)
        r = self.race.step(act)
        live = self.agents
        term = {a: bool(r.terminated[0, self._index[a]]) for a in live}
        trunc = {a: bool(r.truncated[0, self._index[a]]) for a in live}
        self.agents = [a for a in live if not (term[a] or trunc[a])]
        # the world auto-reset in RaceEnv once nobody races: report the states reached instead
        obs_t = final_observations(self.race, r) if not self.agents else r.obs
        obs = {a: obs_t[0, self._index[a]].numpy().copy() for a in live}
        rew = {a: float(r.reward[0, self._index[a]]) for a in live}
        info = {a: {k: float(v[0, self._index[a]]) for k, v in r.terms.items()} for a in live}
        if r.stats:
            for a in live:
                info[a]["episode"] = dict(r.stats)
        return obs, rew, term, trunc, info

    def state(self) -> np.ndarray:
        """The world's joint observation: every drone's observation, concatenated (the critics' input)."""
        obs, _ = self.race.observe()
        return obs[0].reshape(-1).numpy().copy()


class RaceParallelVectorEnv(_RaceAgents):
    """N worlds of one RaceEnv behind PettingZoo's parallel dict API, every value batched over the
    worlds: the vectorized form of RaceParallelEnv (one world per environment costs a whole RaceEnv
    step per world; docs/envs.md). Same-step autoreset, as RaceVectorEnv.

    reset(seed) -> obs {agent: (N, D)}, infos {agent: {}}
    step({agent: (N, 4)}) -> obs {agent: (N, D)}, rewards {agent: (N,)}, terminations {agent: (N,)},
        truncations {agent: (N,)}, infos {agent: {"alive": (N,) the drone raced in this step,
        "final_obs": (N, D) the state reached before a world's reset, "_final_obs": (N,) the world
        reset (its race ended: time-out or every drone down)}}
    A drone that crashed stays down (alive False, reward 0, actions ignored) until its world resets.
    """

    metadata = {"name": "cfrace_race_vector_v0", "render_modes": [], "autoreset_mode": "SameStep"}

    def __init__(self, num_envs: int = 64, method: str = "ours", track: str = "lemniscate", obstacles: bool = False,
                 seed: int = 0, **kw: Any):
        self._build(method, track, num_envs, obstacles, seed, kw)
        self.num_envs = num_envs
        self.agents = self.possible_agents[:]

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            reseed(self.race, seed)
        obs, _ = self.race.reset()
        return {a: obs[:, i].numpy().copy() for i, a in enumerate(self.agents)}, {a: {} for a in self.agents}

    def step(self, actions: dict[str, Any]):
        act = torch.zeros(self.num_envs, self.race.num_agents, 4)
        for a, v in actions.items():
            act[:, self._index[a]] = torch.as_tensor(np.asarray(v, np.float32)).reshape(-1, 4)
        r = self.race.step(act)
        # a world reset when every drone is down or done in this step (RaceEnv's own rule, seen from outside)
        reset = (r.terminated | r.truncated | ~r.alive).all(-1).numpy()
        final = final_observations(self.race, r)
        out = {}
        for i, a in enumerate(self.agents):
            out[a] = (r.obs[:, i].numpy().copy(), r.reward[:, i].numpy().copy(), r.terminated[:, i].numpy().copy(),
                      r.truncated[:, i].numpy().copy(),
                      {"alive": r.alive[:, i].numpy().copy(), "final_obs": final[:, i].numpy().copy(),
                       "_final_obs": reset.copy()})
        if r.stats:
            for a in self.agents:
                out[a][4]["episode"] = dict(r.stats)
        return tuple({a: out[a][k] for a in self.agents} for k in range(5))
