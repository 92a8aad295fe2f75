"""Training-start settings for sparse runs from scratch (docs/training.md, "Sparse from scratch: the
exploration noise"): --start-speed and --set init_std, recorded in the checkpoint and the exported policy."""

from __future__ import annotations

import torch

from cfrace.export import export_checkpoint
from cfrace.policy import OnnxPolicy
from cfrace.rl.train import TrainConfig, make_env, train


def test_start_speed_is_in_the_training_metadata():
    for speed, expected in ((0.0, None), (2.5, 2.5)):
        env, meta = make_env(TrainConfig("ss", "lemniscate", start_speed=speed), torch.device("cpu"), 4)
        assert env.start_speed == speed and meta.get("start_speed") == expected


def test_a_run_with_flying_starts_and_a_set_action_std_exports_both(tmp_path):
    small = (("actor_hidden", (16, 16)), ("critic_hidden", (16,)))
    cfg = TrainConfig("ss", "lemniscate", num_envs=8, steps=8 * 24, device="cpu", threads=1, seed=3,
                      out=str(tmp_path / "run"), start_speed=3.0, overrides=small + (("init_std", 0.3),))
    res = train(cfg)
    _, meta, _ = export_checkpoint(res.checkpoint, tmp_path / "p.onnx")
    onnx_meta = OnnxPolicy(tmp_path / "p.onnx").meta
    assert meta["start_speed"] == 3.0 == onnx_meta["start_speed"]
    assert meta["init_std"] == 0.3 == onnx_meta["init_std"]
    plain = TrainConfig("ss", "lemniscate", num_envs=8, steps=8 * 24, device="cpu", threads=1, seed=3,
                        out=str(tmp_path / "plain"), overrides=small)
    _, meta, _ = export_checkpoint(train(plain).checkpoint, tmp_path / "q.onnx")
    assert "start_speed" not in meta and "init_std" not in meta       # the defaults: nothing to record
