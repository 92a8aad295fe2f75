"""The batched RaceEnv behind standard interfaces, for trainers other than cfrace's own.

    RaceGymEnv        gymnasium.Env, one world, single-agent methods (ds, ss)
    RaceVectorEnv     gymnasium.vector.VectorEnv, N worlds in one RaceEnv (same-step autoreset)
    RaceParallelEnv   pettingzoo ParallelEnv, one world, every drone of the method an agent
    RaceParallelVectorEnv   the same dict API over N worlds, every value batched (the vectorized form)

They only convert: tensors to NumPy, agents to dicts, RaceEnv's auto-reset to each API's episode
rules. Physics, observations, rewards, dones and resets are RaceEnv's (cfrace/env/race_env.py),
built by the same function as `cfrace train` (cfrace.rl.train.make_env). Needs the `envs` extra:
pip install "cfrace[envs]".
"""

from __future__ import annotations

import numpy as np
import torch

from cfrace.errors import ConfigError

AGENT_PREFIX = "drone_"


def make_race_env(method: str, track: str = "lemniscate", num_envs: int = 1, obstacles: bool = False, seed: int = 0,
                  profile: str | None = None, episode_s: float = 30.0, random_phase: bool = False,
                  flight_obs: bool = False):
    """(RaceEnv, metadata) on the CPU, exactly as `cfrace train` builds it (domain randomisation on)."""
    from cfrace.rl.train import TrainConfig, make_env

    kw = {"profile": profile} if profile is not None else {}
    cfg = TrainConfig(method, track, obstacles, num_envs=num_envs, seed=seed, episode_s=episode_s,
                      random_phase=random_phase, flight_obs=flight_obs, **kw)
    return make_env(cfg, torch.device("cpu"), num_envs)


def reseed(env, seed: int) -> None:
    """Reseed the RaceEnv's own generators (spawn, randomisation) and its simulator's."""
    env.gen.manual_seed(int(seed))
    env.sim.generator.manual_seed(int(seed))


def final_observations(env, result) -> torch.Tensor:
    """(E, A, obs_dim) observations of the states reached in this step, before RaceEnv's auto-reset
    (the critic observation starts with the drone's own observation)."""
    return result.final_critic[..., : env.obs_dim]


def spaces(env):
    """(observation, action) Box spaces of one drone: raw observations, actions in [-1, 1]^4."""
    from gymnasium.spaces import Box

    obs = Box(-np.inf, np.inf, (env.obs_dim,), np.float32)
    act = Box(-1.0, 1.0, (4,), np.float32)
    return obs, act


def require_single_agent(env) -> None:
    if env.num_agents != 1:
        raise ConfigError(f"method {env.method!r} races two drones: use RaceParallelEnv (PettingZoo) for it; "
                          f"the Gymnasium environments take the single-agent methods ds and ss")
