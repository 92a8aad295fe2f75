"""Export parity (onnxruntime vs torch, normaliser included) and export-time validation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cfrace.drone import load_profile
from cfrace.contract.actions import action_map_constants
from cfrace.errors import PolicyError
from cfrace.export import export_actor, parity_check, torch_reference
from cfrace.policy import OnnxPolicy
from cfrace.rl.models import AgentModels


def _meta(obs_dim=42, layout="race42", obstacles=False, method="ours"):
    return {"method": method, "track": "complex", "obstacles": obstacles, "obs_layout": layout, "obs_dim": obs_dim,
            **action_map_constants(load_profile("cf2x_paper")), "policy_hz": 50.0, "drone_profile": "cf2x_paper",
            "train_steps": 123, "seed": 4, "cfrace_version": "0.1.0", "agent": "adversary"}


def _trained_like(obs_dim, seed=0):
    torch.manual_seed(seed)
    m = AgentModels(obs_dim, 2 * obs_dim, [64, 32], [32], init_std=0.5)
    with torch.no_grad():  # make the output layer non-trivial (it starts near zero)
        m.actor.mean_net[-1].weight.normal_(0, 0.3)
        m.actor.mean_net[-1].bias.normal_(0, 0.3)
    # normaliser statistics far from (0, 1), with one nearly constant dimension
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(5000, obs_dim, generator=gen) * torch.linspace(0.01, 5, obs_dim) + torch.linspace(-3, 8, obs_dim)
    x[:, 3] = 0.25
    m.obs_norm.update(x)
    return m


@pytest.mark.parametrize("obs_dim,layout,obstacles", [(42, "race42", False), (45, "race45_obstacles", True)])
def test_parity_with_normaliser(tmp_path, obs_dim, layout, obstacles):
    m = _trained_like(obs_dim)
    path = export_actor(m.actor, m.obs_norm, _meta(obs_dim, layout, obstacles), tmp_path / "a.onnx")
    gen = np.random.default_rng(0)
    obs = (m.obs_norm.mean.numpy() + np.sqrt(m.obs_norm.var.numpy()) * gen.normal(size=(1000, obs_dim)) * 3)
    obs = obs.astype(np.float32)
    err = parity_check(path, m.actor, m.obs_norm, obs=obs)
    assert err < 1e-5
    ref = torch_reference(m.actor, m.obs_norm, torch.from_numpy(obs))
    assert ref.std() > 0.1 and (ref.abs() == 1).any()  # the test exercises clipping and real outputs
    # the graph's reference equals the training-time forward pass (mean action, clipped)
    train = m.actor(m.obs_norm(torch.from_numpy(obs))).mean.clamp(-1, 1)
    assert (train - ref).abs().max() < 1e-6
    # the normaliser is really inside the graph: a plain forward without it differs
    plain = m.actor.mean_net(torch.from_numpy(obs)).clamp(-1, 1).detach().numpy()
    assert np.abs(OnnxPolicy(path)(obs) - plain).max() > 1e-2
    # tuple normaliser and random-obs parity helper
    path2 = export_actor(m.actor, (m.obs_norm.mean, m.obs_norm.var), _meta(obs_dim, layout, obstacles),
                         tmp_path / "b.onnx")
    assert parity_check(path2, m.actor, m.obs_norm) < 1e-5


def test_metadata_roundtrip(tmp_path):
    m = _trained_like(42)
    pol = OnnxPolicy(export_actor(m.actor, None, _meta(), tmp_path / "a.onnx"))
    assert pol.meta["agent"] == "adversary" and pol.meta["train_steps"] == 123 and pol.meta["seed"] == 4
    assert pol.meta["max_rates_deg"] == [100.0, 100.0, 200.0] and pol.meta["max_thrust_weights"] == 3.15
    assert parity_check(tmp_path / "a.onnx", m.actor, None) < 1e-5


def test_export_refuses_bad_input(tmp_path):
    m = _trained_like(42)
    with pytest.raises(PolicyError):
        export_actor(m.actor, m.obs_norm, _meta(45, "race45_obstacles", True), tmp_path / "x.onnx")
    bad = _meta()
    del bad["seed"]
    with pytest.raises(PolicyError):
        export_actor(m.actor, m.obs_norm, bad, tmp_path / "y.onnx")
    with pytest.raises(TypeError):
        export_actor(torch.nn.Sequential(torch.nn.Linear(42, 4), torch.nn.GELU()), None, _meta(), tmp_path / "z.onnx")
    assert not list(tmp_path.glob("*.onnx"))
