"""Parked opponents in training (`cfrace train --parked-opponent-frac`): in that share of the races
the last drone starts crashed, at rest on the floor below its start slot, which is what a policy
flying alone sees of its stopped opponent in the flight stack's dry-run; the others race nobody."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from cfrace.drone import load_profile
from cfrace.env.race_env import RaceEnv
from cfrace.errors import ConfigError
from cfrace.track import load_track

CFRACE = Path(sys.executable).with_name("cfrace")


def _env(parked_frac: float = 0.0, envs: int = 64, seed: int = 3, **kw) -> RaceEnv:
    return RaceEnv(load_track("lemniscate"), load_profile("cf2x_paper"), num_envs=envs, method="ours",
                   obstacles=False, seed=seed, parked_frac=parked_frac, **kw)


def test_parked_drones_start_crashed_on_the_floor_and_stay_there():
    env = _env(0.5)
    env.reset()
    parked = env.parked.clone()
    assert not parked[:, 0].any()                     # only the last slot is ever parked
    assert 0 < int(parked[:, 1].sum()) < env.num_envs  # a share of the worlds, drawn per race
    assert torch.equal(env.sim.race.crashed, parked)
    at_rest = env.sim.pos[parked].clone()
    assert torch.all(at_rest[:, 2] == env.sim.z_rest)
    hover = torch.zeros(env.num_envs, 2, 4)
    for _ in range(10):
        res = env.step(hover)
        assert not res.alive[parked].any()                       # a parked drone never acts
        assert not res.reward[parked].any()
    kept = parked & (env.steps == 10).unsqueeze(-1)              # worlds that did not reset meanwhile
    assert kept.any() and torch.equal(env.sim.pos[kept], at_rest[kept[parked]])


def test_a_world_with_a_parked_opponent_runs_until_its_racer_is_done():
    env = _env(0.999, envs=8, episode_s=1.0)
    env.reset()
    assert env.parked[:, 1].all()
    stats = []
    for _ in range(int(1.0 / 0.02)):
        res = env.step(torch.zeros(8, 2, 4))
        racer_done = res.terminated[:, 0] | res.truncated[:, 0]
        assert torch.equal(env.steps == 0, racer_done)           # a world resets when its racer is done, then only
        stats += [res.stats] if res.stats else []
    assert stats and res.truncated[:, 0].any()                   # the last step: the time-out
    assert all(0.0 <= s["crash_rate"] <= 1.0 for s in stats)
    assert stats[-1]["crash_rate"] < 1.0                          # of the drones that flew: not the parked ones


def test_no_parking_keeps_the_random_stream_of_runs_before_it():
    a, b = _env(0.0, envs=16), RaceEnv(load_track("lemniscate"), load_profile("cf2x_paper"), num_envs=16,
                                       method="ours", obstacles=False, seed=3)
    oa, ob = a.reset()[0], b.reset()[0]
    assert torch.equal(oa, ob)
    for _ in range(60):
        act = torch.rand(16, 2, 4) * 2 - 1
        assert torch.equal(a.step(act).obs, b.step(act).obs)
    assert not a.parked.any()


def test_parked_frac_is_refused_out_of_range_or_for_one_drone():
    with pytest.raises(ConfigError, match=r"\[0, 1\)"):
        _env(1.0)
    with pytest.raises(ConfigError, match="multi-agent"):
        RaceEnv(load_track("lemniscate"), load_profile("cf2x_paper"), num_envs=2, method="ds", obstacles=False,
                parked_frac=0.3)


def test_the_option_refuses_bad_input_in_one_line_and_is_recorded_in_the_policy(tmp_path):
    env = dict(os.environ, COLUMNS="200")
    for extra, word in [(["--method", "ours", "--parked-opponent-frac", "1.5"], "[0, 1)"),
                        (["--method", "ours", "--parked-opponent-frac", "-0.1"], "[0, 1)"),
                        (["--method", "ds", "--parked-opponent-frac", "0.3"], "multi-agent")]:
        r = subprocess.run([str(CFRACE), "train", "--track", "lemniscate", "--steps", "10",
                            "--out", str(tmp_path / "bad"), *extra], capture_output=True, text=True, env=env,
                           timeout=240, cwd=tmp_path)
        assert r.returncode == 2 and "Traceback" not in r.stderr and r.stderr.count("\n") == 1, r.stderr
        assert word in r.stderr and "--parked-opponent-frac" in r.stderr, r.stderr
        assert not (tmp_path / "bad").exists()
    from cfrace.export import export_checkpoint
    from cfrace.policy import OnnxPolicy
    from cfrace.rl.train import TrainConfig, train
    small = (("actor_hidden", (16, 16)), ("critic_hidden", (16,)))
    cfg = TrainConfig("ours", "lemniscate", num_envs=8, steps=8 * 24, device="cpu", threads=1, seed=3,
                      out=str(tmp_path / "run"), overrides=small, parked_opponent_frac=0.25)
    export_checkpoint(train(cfg).checkpoint, tmp_path / "p.onnx", agent="ego")
    assert OnnxPolicy(tmp_path / "p.onnx").meta["parked_opponent_frac"] == 0.25
