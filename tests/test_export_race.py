"""Real pipeline on RaceEnv: train one small iteration, export, and run the ONNX policy on the env's
own observations (the same numbers the torch actor gives)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cfrace.drone import load_profile
from cfrace.env.race_env import RaceEnv
from cfrace.export import export_checkpoint
from cfrace.policy import OnnxPolicy
from cfrace.rl.models import AgentModels
from cfrace.rl.config import IPPOConfig
from cfrace.rl.train import TrainConfig, load_checkpoint, train
from cfrace.track import load_track


@pytest.fixture(autouse=True)
def _threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("method,obstacles,layout", [("ours", True, "race45_obstacles"), ("ds", False, "solo36")])
def test_train_export_fly(tmp_path, method, obstacles, layout):
    cfg = TrainConfig(method, "complex", obstacles, num_envs=32, steps=1, out=str(tmp_path / "run"),
                      device="cpu", threads=1, seed=7,
                      overrides=(("actor_hidden", (32, 32)), ("critic_hidden", (32,)), ("epochs", 1)))
    res = train(cfg)
    assert res.iterations == 1 and res.exact_resume is None
    path, meta, err = export_checkpoint(res.checkpoint, tmp_path / "p.onnx", "best")
    pol = OnnxPolicy(path)
    pol.check("complex", obstacles)
    assert pol.meta["obs_layout"] == layout and pol.meta["method"] == method and err < 1e-5
    # the exported policy on real observations equals the torch actor's clipped mean
    ck = load_checkpoint(res.checkpoint)
    ippo = IPPOConfig.from_dict(ck["runner"]["ippo"])
    model = AgentModels(meta["obs_dim"], ck["meta"]["critic_dim"], ippo.actor_hidden, ippo.critic_hidden, 1.0)
    model.load_state_dict(ck["runner"]["agents"][meta["agent_index"]])
    env = RaceEnv(load_track("complex"), load_profile("cf2x_paper"), num_envs=16, method=method, obstacles=obstacles,
                  randomize=False, seed=1)
    obs, _ = env.reset()
    for _ in range(20):
        flat = obs.reshape(-1, obs.shape[-1])
        onnx_a = pol(flat.numpy())
        with torch.no_grad():
            torch_a = model.actor(model.obs_norm(flat)).mean.clamp(-1, 1).numpy()
        assert np.abs(onnx_a - torch_a).max() < 1e-5
        obs = env.step(torch.from_numpy(onnx_a).reshape(obs.shape[0], obs.shape[1], 4)).obs
