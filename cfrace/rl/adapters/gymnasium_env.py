"""Gymnasium interfaces of the race for the single-agent methods (ds, ss).

RaceGymEnv is one world (gymnasium.Env, passes gymnasium.utils.env_checker.check_env);
RaceVectorEnv is N worlds stepped as one batch by one RaceEnv (gymnasium.vector.VectorEnv with
same-step autoreset: a finished world's next observation is already its new episode's, the
finished episode's last observation is in infos["final_obs"] as in gymnasium's SyncVectorEnv).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from cfrace.rl.adapters import final_observations, make_race_env, require_single_agent, reseed, spaces


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy().copy()


class RaceGymEnv(gym.Env):
    """One world of RaceEnv, one drone. obs (obs_dim,) float32, action (4,) in [-1, 1]."""

    metadata = {"render_modes": []}

    def __init__(self, method: str = "ds", track: str = "lemniscate", obstacles: bool = False, seed: int = 0,
                 **kw: Any):
        self.race, self.meta = make_race_env(method, track, 1, obstacles, seed, **kw)
        require_single_agent(self.race)
        self.observation_space, self.action_space = spaces(self.race)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            reseed(self.race, seed)
        obs, _ = self.race.reset()
        return _np(obs[0, 0]), {}

    def step(self, action):
        act = torch.as_tensor(np.asarray(action, np.float32)).reshape(1, 1, 4)
        r = self.race.step(act)
        terminated, truncated = bool(r.terminated[0, 0]), bool(r.truncated[0, 0])
        # the world auto-resets in RaceEnv when done: hand back the observation of the state reached
        obs = final_observations(self.race, r) if (terminated or truncated) else r.obs
        info = {k: float(v[0, 0]) for k, v in r.terms.items()}
        if r.stats:
            info["episode"] = dict(r.stats)
        return _np(obs[0, 0]), float(r.reward[0, 0]), terminated, truncated, info


class RaceVectorEnv(VectorEnv):
    """``num_envs`` worlds of one RaceEnv (one drone each), stepped as one batch.

    obs (N, obs_dim) float32, actions (N, 4), rewards (N,) float32, terminations/truncations (N,)
    bool; infos["final_obs"] (object array, the finished episodes' last observations) with mask
    infos["_final_obs"]; infos["episode"] RaceEnv's statistics of the episodes that ended."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 64, method: str = "ds", track: str = "lemniscate", obstacles: bool = False,
                 seed: int = 0, **kw: Any):
        self.race, self.meta = make_race_env(method, track, num_envs, obstacles, seed, **kw)
        require_single_agent(self.race)
        self.num_envs = num_envs
        self.single_observation_space, self.single_action_space = spaces(self.race)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._np_random, self._np_random_seed = gym.utils.seeding.np_random(seed)
            reseed(self.race, seed)
        obs, _ = self.race.reset()
        return _np(obs[:, 0]), {}

    def step(self, actions):
        act = torch.as_tensor(np.asarray(actions, np.float32)).reshape(self.num_envs, 1, 4)
        r = self.race.step(act)
        terminated, truncated = _np(r.terminated[:, 0]), _np(r.truncated[:, 0])
        infos: dict[str, Any] = {}
        done = terminated | truncated
        if done.any():
            final = _np(final_observations(self.race, r)[:, 0])
            objs = np.full(self.num_envs, None, dtype=object)
            for i in np.flatnonzero(done):
                objs[i] = final[i]
            infos["final_obs"], infos["_final_obs"] = objs, done
        if r.stats:
            infos["episode"] = dict(r.stats)
        return _np(r.obs[:, 0]), _np(r.reward[:, 0]), terminated, truncated, infos
