"""Warm start: a single-agent actor copied into both racers acts exactly like its source."""

from __future__ import annotations

import types

import torch

from cfrace.drone import load_profile
from cfrace.env.race_env import RaceEnv
from cfrace.rl.models import AgentModels
from cfrace.rl.train import FORMAT
from cfrace.rl.warmstart import OPP_POS_VAR, OPP_VEL_VAR, warm_start
from cfrace.track import load_track


def test_warm_started_racers_act_like_the_single_agent_source(tmp_path):
    torch.manual_seed(0)
    src = AgentModels(36, 36, (32, 32), (32,), 0.5)
    src.obs_norm.update(torch.randn(500, 36) * 3 + 1)
    ckpt = {"format": FORMAT, "meta": {"obs_layout": "solo36"},
            "runner": {"agents": [src.state_dict()], "total_reward": torch.tensor([1.0]), "env_steps": 123}}
    torch.save(ckpt, tmp_path / "checkpoint.pt")

    env = RaceEnv(load_track("lemniscate"), load_profile("cf2x_paper"), num_envs=8, method="ours", obstacles=False)
    obs, _ = env.reset()
    agents = [AgentModels(42, 84, (32, 32), (32,), 1.0) for _ in range(2)]
    for a in agents:  # as the runner does at start: the first reset batch (tiny opponent variance)
        a.obs_norm.update(obs[:, 0])
    runner = types.SimpleNamespace(agents=agents)
    info = warm_start(runner, tmp_path, "race42")
    assert info["init_env_steps"] == 123 and info["init_agent"] == 0

    x = torch.randn(64, 42) * 2
    with torch.no_grad():
        want = src.actor(src.obs_norm(x[:, :36])).mean
        for a in agents:
            got = a.actor(a.obs_norm(x)).mean
            assert torch.allclose(got, want, atol=1e-6)  # the opponent inputs have no effect yet
            assert torch.equal(a.obs_norm.count, src.obs_norm.count)
            assert torch.allclose(a.obs_norm.var[36:], torch.tensor([OPP_POS_VAR] * 3 + [OPP_VEL_VAR] * 3,
                                                                    dtype=torch.float64))
            assert torch.all(a.obs_norm.mean[36:] == 0)
