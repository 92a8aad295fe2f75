"""Settings tried on sparse runs from scratch (docs/training.md, "Sparse from scratch"; the runs in
studies/training/sparse_from_scratch.md): the discount, the actor's initial std and the schedule of its cap
(--set gamma / init_std / std_final / std_anneal_iters); what the schedule does and that the exported policy records them."""

from __future__ import annotations

import pytest
import torch

from cfrace.errors import ConfigError
from cfrace.export import export_checkpoint
from cfrace.policy import OnnxPolicy
from cfrace.rl.checkpoint import load_checkpoint
from cfrace.rl.config import parse_overrides, preset, std_cap
from cfrace.rl.models import Actor
from cfrace.rl.train import TrainConfig, train

SCHEDULE = (("std_final", 0.2), ("std_anneal_iters", 4))


def test_the_exported_policy_records_a_set_discount_action_std_and_schedule(tmp_path):
    small = (("actor_hidden", (16, 16)), ("critic_hidden", (16,)))
    cfg = TrainConfig("ss", "lemniscate", num_envs=8, steps=8 * 24 * 3, device="cpu", threads=1, seed=3,
                      out=str(tmp_path / "run"), overrides=small + (("init_std", 0.6), ("gamma", 0.995)) + SCHEDULE)
    stds = []
    res = train(cfg, on_iteration=lambda m, info: stds.append(m["std_agent0"]))
    caps = [0.6, 0.5, 0.4]                                           # the cap, 0.6 -> 0.2 over 4 iterations
    assert [std_cap(preset("cpu", False, cfg.overrides), i) for i in range(3)] == pytest.approx(caps)
    assert all(s <= c + 1e-6 for s, c in zip(stds, caps))              # it never samples above the cap
    log_std = load_checkpoint(res.checkpoint)["runner"]["agents"][0]["actor.log_std"]
    # where the learned parameter lies above the cap the std is the cap; below it, the parameter
    assert stds[-1] == pytest.approx(float(log_std.exp().clamp(max=caps[-1]).mean()), abs=1e-6)
    _, meta, _ = export_checkpoint(res.checkpoint, tmp_path / "p.onnx")
    onnx_meta = OnnxPolicy(tmp_path / "p.onnx").meta
    assert meta["init_std"] == 0.6 == onnx_meta["init_std"]
    assert (onnx_meta["std_final"], onnx_meta["std_anneal_iters"]) == (0.2, 4)
    assert meta["gamma"] == 0.995 == onnx_meta["gamma"]
    plain = TrainConfig("ss", "lemniscate", num_envs=8, steps=8 * 24, device="cpu", threads=1, seed=3,
                        out=str(tmp_path / "plain"), overrides=small)
    _, meta, _ = export_checkpoint(train(plain).checkpoint, tmp_path / "q.onnx")
    assert not {"init_std", "std_final", "std_anneal_iters", "gamma"} & set(meta)   # the defaults: nothing to record


def test_std_cap_schedule_and_what_the_actor_samples_with():
    cfg = preset("cpu", False, parse_overrides(["std_final=0.2", "std_anneal_iters=100"]))
    assert [std_cap(cfg, i) for i in (0, 50, 100, 500)] == pytest.approx([1.0, 0.6, 0.2, 0.2])
    assert std_cap(preset("cpu", False), 7) is None                        # default: no cap
    actor = Actor(36, (8,), init_std=1.0)
    with torch.no_grad():
        actor.log_std[:] = torch.log(torch.tensor([1.0, 0.5, 0.1, 2.0]))
    dist = actor(torch.zeros(3, 36))
    assert torch.allclose(dist.stddev[0], torch.tensor([1.0, 0.5, 0.1, 2.0]))
    actor.std_max = 0.4
    assert torch.allclose(actor(torch.zeros(3, 36)).stddev[0], torch.tensor([0.4, 0.4, 0.1, 0.4]))
    actor(torch.zeros(3, 36)).log_prob(torch.zeros(3, 4)).sum().backward()
    assert actor.log_std.grad[2] != 0 and actor.log_std.grad[0] == 0     # below the cap it still learns
    with pytest.raises(ConfigError):
        parse_overrides(["std_anneal_iters=0.5"])
    assert parse_overrides(["std_final=none"]) == (("std_final", None),)


def test_reward_weights_from_the_command_line_change_the_reward_and_are_recorded(tmp_path):
    """`cfrace train --reward gate=10` (ours from scratch: docs/training.md): a drone that passes a gate
    while not leading earns 10 instead of the paper's 5; the weights reach the checkpoint, the
    exported metadata and a resumed run; bad ones are refused with one line."""
    from cfrace.env.rewards import RewardInputs, parse_reward_overrides, reward_scales, reward_terms
    from cfrace.rl.train import resume_config

    assert parse_reward_overrides(["gate=10", "crash=4"]) == (("gate", 10.0), ("crash", 4.0))
    for bad in (["gate"], ["gate=x"], ["gate=nan"], ["nope=1"]):
        with pytest.raises(ConfigError, match="--reward"):
            parse_reward_overrides(bad)
    one = torch.ones(1, 2)
    x = RewardInputs(torch.zeros(1, 2, 4), one.long(), one.bool() & False, torch.tensor([[True, False]]),
                     one.bool() & False, one.bool() & False, one * 0, one * 0, 0.02)
    assert reward_terms("ours", x)["gate"].tolist() == [[10.0, 5.0]]
    assert reward_terms("ours", x, reward_scales((("gate", 10.0),)))["gate"].tolist() == [[10.0, 10.0]]
    small = (("actor_hidden", (16, 16)), ("critic_hidden", (16,)))
    cfg = TrainConfig("ours", "lemniscate", num_envs=8, steps=8 * 16 * 2, device="cpu", threads=1, seed=3,
                      out=str(tmp_path / "run"), overrides=small, rewards=(("gate", 10.0),))
    res = train(cfg)
    _, meta, _ = export_checkpoint(res.checkpoint, tmp_path / "p.onnx")
    assert meta["rewards"] == {"gate": 10.0} == OnnxPolicy(tmp_path / "p.onnx").meta["rewards"]
    assert resume_config(res.checkpoint, steps=8 * 16 * 3).rewards == (("gate", 10.0),)
    _, plain, _ = export_checkpoint(train(TrainConfig("ss", "lemniscate", num_envs=8, steps=8 * 24, device="cpu",
                                                      threads=1, seed=3, out=str(tmp_path / "plain"),
                                                      overrides=small)).checkpoint, tmp_path / "q.onnx")
    assert "rewards" not in plain
