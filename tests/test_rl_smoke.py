"""Seconds-long training on the real RaceEnv shows learning."""

from __future__ import annotations

import pytest
import torch

from cfrace.drone import load_profile
from cfrace.env.race_env import RaceEnv
from cfrace.rl.config import preset
from cfrace.rl.runner import Runner
from cfrace.track import load_track


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _evaluate(runner: Runner, track, profile, steps: int = 50) -> float:
    """Mean 1-s return of the deterministic (mean-action) policy from 64 fixed, nominal starts."""
    env = RaceEnv(track, profile, num_envs=64, method="ds", obstacles=False, randomize=False, seed=123,
                  episode_s=steps * 0.02)
    obs, _ = env.reset()
    total = torch.zeros(64)
    model = runner.agents[0]
    for _ in range(steps):
        with torch.no_grad():
            action = model.actor(model.obs_norm(obs[:, 0])).mean[:, None]
        res = env.step(action)
        obs = res.obs
        total += res.reward[:, 0]
    return float(total.mean())


@pytest.mark.slow
def test_dense_single_agent_learns_in_seconds():
    track, profile = load_track("complex"), load_profile("cf2x_paper")
    env = RaceEnv(track, profile, num_envs=256, method="ds", obstacles=False, seed=0, episode_s=3.0)
    cfg = preset("cpu", False, num_envs=256, rollout=24, actor_hidden=(64, 64), critic_hidden=(64, 64))
    runner = Runner(env, cfg, seed=0)
    before = _evaluate(runner, track, profile)
    after = []
    for k in range(12):
        runner.iterate()
        if k in (7, 11):
            after.append(_evaluate(runner, track, profile))
    # untrained: full thrust up into the ceiling (crash -10); trained: flies toward the gate. What 12
    # iterations learn depends on the CPU's float path (here -58 -> +45 after 8, +7 or +11 after 12 with
    # 1 or 2 threads): the test asserts the learning, not one CPU's figure: better than untrained at
    # the end, and by far at the better of two evaluations
    assert before < -20.0, before
    assert after[-1] > before and max(after) > before + 30.0, (before, after)
