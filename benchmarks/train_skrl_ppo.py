"""Train DS (dense single-agent reward) on the lemniscate with a third-party trainer: skrl's PPO
(the library the paper's authors used) on cfrace's Gymnasium vector environment.

    pip install "cfrace[envs]" skrl
    python benchmarks/train_skrl_ppo.py --minutes 3 [--worlds 256] [--out runs/skrl_ds]

cfrace provides only the environment (RaceVectorEnv: 256 worlds of the batched RaceEnv in one
gymnasium.vector.VectorEnv); models, PPO, memory, logging and the trainer loop are skrl's. The
episode statistics RaceEnv reports (gates/s, share of races with a lap, crash rate...) reach
skrl's TensorBoard logs through infos["episode"]. At the end the script prints how the mean
action flies 64 fresh races before and after training (return, flight time, crashes).
"""

from __future__ import annotations

import argparse
import time

import gymnasium
import torch
from torch import nn


class EpisodeStatsForSkrl(gymnasium.vector.VectorWrapper):
    """Hands RaceEnv's episode statistics to skrl's trainer the way it logs them: one-element
    tensors under infos["episode"] (TensorBoard tags "Race / gates_per_s", ...)."""

    def step(self, actions):
        obs, rew, term, trunc, infos = self.env.step(actions)
        if "episode" in infos:
            infos["episode"] = {f"Race / {k}": torch.tensor(v) for k, v in infos["episode"].items()}
        return obs, rew, term, trunc, infos


def build(worlds: int, seed: int, rollouts: int, out: str):
    from skrl.agents.torch.ppo import PPO, PPO_CFG
    from skrl.envs.wrappers.torch import wrap_env
    from skrl.memories.torch import RandomMemory
    from skrl.models.torch import DeterministicMixin, GaussianMixin, Model
    from skrl.resources.preprocessors.torch import RunningStandardScaler
    from skrl.resources.schedulers.torch import KLAdaptiveLR

    from cfrace.rl.adapters.gymnasium_env import RaceVectorEnv

    class Policy(GaussianMixin, Model):
        def __init__(self, observation_space, action_space, device):
            Model.__init__(self, observation_space=observation_space, action_space=action_space, device=device)
            GaussianMixin.__init__(self, clip_actions=False, clip_log_std=True, min_log_std=-5.0, max_log_std=1.0)
            self.net = nn.Sequential(nn.Linear(self.num_observations, 128), nn.ELU(), nn.Linear(128, 128), nn.ELU(),
                                     nn.Linear(128, self.num_actions))
            self.log_std = nn.Parameter(torch.zeros(self.num_actions))

        def compute(self, inputs, role=""):
            return self.net(inputs["observations"]), {"log_std": self.log_std}

    class Value(DeterministicMixin, Model):
        def __init__(self, observation_space, action_space, device):
            Model.__init__(self, observation_space=observation_space, action_space=action_space, device=device)
            DeterministicMixin.__init__(self)
            self.net = nn.Sequential(nn.Linear(self.num_observations, 256), nn.ELU(), nn.Linear(256, 128), nn.ELU(),
                                     nn.Linear(128, 1))

        def compute(self, inputs, role=""):
            return self.net(inputs["observations"]), {}

    venv = RaceVectorEnv(worlds, "ds", "lemniscate", seed=seed)
    env = wrap_env(EpisodeStatsForSkrl(venv), wrapper="gymnasium")
    device = env.device
    models = {"policy": Policy(env.observation_space, env.action_space, device),
              "value": Value(env.observation_space, env.action_space, device)}
    cfg = PPO_CFG(rollouts=rollouts, learning_epochs=5, mini_batches=4, discount_factor=0.99, gae_lambda=0.95,
                  learning_rate=5e-4, learning_rate_scheduler=KLAdaptiveLR,
                  learning_rate_scheduler_kwargs={"kl_threshold": 0.01}, grad_norm_clip=1.0, ratio_clip=0.2,
                  value_clip=0.0, value_loss_scale=1.0,
                  entropy_loss_scale=0.0, time_limit_bootstrap=True,
                  observation_preprocessor=RunningStandardScaler,
                  observation_preprocessor_kwargs={"size": env.observation_space, "device": device},
                  experiment={"directory": out, "experiment_name": "ppo", "write_interval": rollouts,
                              "checkpoint_interval": 0})
    memory = RandomMemory(memory_size=rollouts, num_envs=env.num_envs, device=device)
    agent = PPO(models=models, memory=memory, observation_space=env.observation_space,
                action_space=env.action_space, device=device, cfg=cfg)
    return venv, env, agent


def evaluate(agent, worlds: int = 64, seed: int = 123, steps: int = 500) -> dict:
    """Mean action, a fresh RaceVectorEnv, each world's first race (up to 10 s): mean return,
    mean duration (s) and the share that crashed."""
    import numpy as np

    from cfrace.rl.adapters.gymnasium_env import RaceVectorEnv

    venv = RaceVectorEnv(worlds, "ds", "lemniscate", seed=seed)
    obs, _ = venv.reset(seed=seed)
    ret, length = np.zeros(worlds), np.zeros(worlds)
    first = np.ones(worlds, bool)                 # still in its first race
    crashed = np.zeros(worlds, bool)
    with torch.no_grad():
        for _ in range(steps):
            mean, _ = agent.policy.compute({"observations": agent._observation_preprocessor(torch.as_tensor(obs))})
            obs, rew, term, trunc, _ = venv.step(mean.clamp(-1, 1).numpy())
            ret += np.where(first, rew, 0.0)
            length += first * 0.02
            crashed |= first & term
            first &= ~(term | trunc)
    return {"return": float(ret.mean()), "race_s": float(length.mean()), "crashed": float(crashed.mean())}


def main() -> None:
    ap = argparse.ArgumentParser(description="skrl PPO on cfrace's Gymnasium vector environment")
    ap.add_argument("--minutes", type=float, default=3.0)
    ap.add_argument("--worlds", type=int, default=256)
    ap.add_argument("--rollouts", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="runs/skrl_ds")
    args = ap.parse_args()
    torch.set_num_threads(1)
    from skrl.trainers.torch import SequentialTrainer

    venv, env, agent = build(args.worlds, args.seed, args.rollouts, args.out)
    # time a few updates, then size the run to the budget (skrl's trainer counts timesteps, not time)
    trainer_cfg = {"disable_progressbar": True, "headless": True, "close_environment_at_exit": False}
    first = 3
    t0 = time.perf_counter()
    before = evaluate(agent)
    t1 = time.perf_counter()
    SequentialTrainer(env=env, agents=agent, cfg={"timesteps": first * args.rollouts, **trainer_cfg}).train()
    per_update = (time.perf_counter() - t1) / first
    updates = max(1, int(args.minutes * 60 / per_update) - first)
    print(f"an update of {args.worlds} worlds x {args.rollouts} steps takes {per_update:.1f} s: "
          f"{updates} more updates for {args.minutes:g} min", flush=True)
    SequentialTrainer(env=env, agents=agent, cfg={"timesteps": updates * args.rollouts, **trainer_cfg}).train()
    after = evaluate(agent)
    steps = (updates + first) * args.rollouts * args.worlds
    wall = time.perf_counter() - t0
    print(f"trained {steps:,} env steps in {wall / 60:.1f} min ({steps / wall:,.0f} env steps/s); "
          f"TensorBoard logs in {agent.experiment_dir}")
    print(f"mean action, 64 races of up to 10 s, before -> after: return {before['return']:.1f} -> "
          f"{after['return']:.1f}, flight time {before['race_s']:.1f} -> {after['race_s']:.1f} s, "
          f"crashed {before['crashed']:.0%} -> {after['crashed']:.0%}")


if __name__ == "__main__":
    main()
