"""Mixed precision of the PPO update (cfrace/rl/precision.py) and `bench train --compare`."""

from __future__ import annotations

import json

import pytest
import torch
from typer.testing import CliRunner

from cfrace.cli.main import app
from cfrace.errors import ConfigError
from cfrace.rl import precision as prec
from cfrace.rl.speed_compare import Config, compare, parse_compare
from cfrace.rl.config import preset
from cfrace.rl.ippo import forward, make_optimizer, ppo_update

pytestmark = pytest.mark.usefixtures("one_torch_thread")

BF16 = prec.Precision("bf16", "bf16", "test")
FP32 = prec.Precision("fp32", "fp32", "test")


SIZES = dict(n=2048, obs_dim=42, critic_dim=84, actor_hidden=(128, 128), critic_hidden=(256, 128))


def _update(make, precision, epochs=2):
    cfg = preset("cpu", multi_agent=True, epochs=epochs, minibatches=4)
    model, batch = make(**SIZES)
    opt = make_optimizer(model, cfg.lr)
    stats, _ = ppo_update(model, opt, batch, cfg, cfg.lr, torch.Generator().manual_seed(0), precision)
    return model, opt, stats


def test_bf16_update_keeps_float32_state_and_follows_the_float32_update(ppo_batch):
    m32, _, s32 = _update(ppo_batch, FP32)
    m16, opt16, s16 = _update(ppo_batch, BF16)
    start = ppo_batch(**SIZES)[0].state_dict()
    # weights, gradients and Adam's moments stay float32
    for p in m16.parameters():
        assert p.dtype == torch.float32 and p.grad is None or p.grad.dtype == torch.float32
    for state in opt16.state.values():
        assert all(v.dtype == torch.float32 for k, v in state.items() if k != "step")
    # the bf16 update moves the weights the same way as the float32 one (bf16 has 8 bits of mantissa)
    for (name, a), b in zip(m32.named_parameters(), m16.parameters()):
        delta32, delta16 = a.detach() - start[name], b.detach() - start[name]
        if delta32.norm() > 0:
            cos = torch.nn.functional.cosine_similarity(delta32.flatten(), delta16.flatten(), dim=0)
            assert cos > 0.9, (name, float(cos))
    # the losses are means over 512 samples: bf16's per-element rounding (2^-9) averages out (1e-5 of
    # them here); rel 5 % leaves 100x for another CPU's bf16 kernels (native or emulated)
    for key in ("surrogate", "value_loss", "entropy"):
        assert s16[key] == pytest.approx(s32[key], rel=0.05, abs=1e-3), key
    # the first minibatch's ratio is 1 up to bf16 rounding: few samples clipped
    assert s16["clip_frac"] < 0.05


def test_bf16_and_fp32_differ_so_the_switch_is_real(ppo_batch):
    m32, _, _ = _update(ppo_batch, FP32, epochs=1)
    m16, _, _ = _update(ppo_batch, BF16, epochs=1)
    w32, w16 = m32.actor.mean_net[0].weight, m16.actor.mean_net[0].weight
    assert not torch.equal(w32, w16)


def test_choose_precision_modes(monkeypatch):
    args = (torch.device("cpu"), 42, 84, (32,), (32,), 256)
    assert prec.choose_precision("fp32", *args).dtype == "fp32"
    assert prec.choose_precision("bf16", *args).dtype == "bf16"
    with pytest.raises(ConfigError, match="--precision 'fp16'"):
        prec.choose_precision("fp16", *args)
    monkeypatch.setattr(prec, "cpu_has_bf16", lambda: False)
    p = prec.choose_precision("auto", *args)
    assert p.dtype == "fp32" and "no bf16" in p.reason and p.fp32_ms is None


def test_auto_measures_where_bf16_exists(monkeypatch):
    monkeypatch.setattr(prec, "cpu_has_bf16", lambda: True)
    p = prec.choose_precision("auto", torch.device("cpu"), 42, 84, (64,), (64,), 512, reps=2)
    assert p.mode == "auto" and p.fp32_ms > 0 and p.bf16_ms > 0
    assert (p.dtype == "bf16") == (p.fp32_ms / p.bf16_ms >= prec.MIN_GAIN)


def test_parse_compare():
    c = parse_compare("precision=fp32,threads=2", {"method": "ds", "threads": 1})
    assert c.rev is None and c.options == {"method": "ds", "threads": "2", "precision": "fp32"}
    assert parse_compare("main", {"method": "ds"}).rev == "main"
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        parse_compare("colour=red", {})


def test_compare_against_a_git_revision_runs_both_trees():
    """HEAD in a temporary worktree against this tree with fp32: two real `bench train` subprocesses."""
    base = {"method": "ds", "track": "lemniscate", "envs": 16, "iterations": 1}
    res = compare(Config("this tree", {**base, "precision": "bf16"}), parse_compare("HEAD", base), rounds=1)
    assert res["a"]["runs"][0]["precision"]["dtype"] == "bf16"
    assert res["b"]["rev"] == "HEAD" and res["b"]["runs"][0]["env_steps_per_s"] > 0
    assert res["ratio_a_over_b"]["env_steps_per_s"] > 0


def test_bench_compare_cli_bad_revision_is_one_line(tmp_path):
    r = CliRunner().invoke(app, ["bench", "train", "--compare", "no-such-rev-xyz", "--envs", "16"])
    assert r.exit_code != 0
    assert isinstance(r.exception, ConfigError) and "not a git revision" in str(r.exception)


def test_bench_train_json_records_precision(tmp_path):
    js = tmp_path / "b.json"
    r = CliRunner().invoke(app, ["bench", "train", "--envs", "16", "--iterations", "1", "--method", "ds",
                                 "--track", "lemniscate", "--precision", "fp32", "--json", str(js)])
    assert r.exit_code == 0, r.output
    assert json.loads(js.read_text())["precision"]["dtype"] == "fp32"


def test_bf16_keeps_the_output_layers_in_float32(ppo_batch):
    """Returns reach thousands: the value head stays float32, so a bf16 hidden layer moves the value by
    a relative 1e-2 at most, not by the whole-number steps of a bf16 output near 4000."""
    model, batch = ppo_batch(**SIZES)
    with torch.no_grad():
        model.critic.net[-1].bias.fill_(4000.0)
        obs_n, critic_n = model.obs_norm(batch["obs"]), model.critic_norm(batch["critic"])
        _, v32 = forward(model, obs_n, critic_n)
        dist16, v16 = forward(model, obs_n, critic_n, lambda: BF16.autocast(torch.device("cpu")))
        whole = model.critic(critic_n)
        with BF16.autocast(torch.device("cpu")):
            all_bf16 = model.critic(critic_n)
    assert v16.dtype == torch.float32 and dist16.mean.dtype == torch.float32
    torch.testing.assert_close(v32, whole)
    # hidden layers in bf16, head in float32: the head's input off by bf16's relative 2^-8 (0.012 here on
    # a value spread of +-2.4; the bound is 80x that, whatever the CPU's bf16 kernels)
    assert (v16 - v32).abs().max() < 1.0
    # what a bf16 head would give: bf16 holds only multiples of 16 in [2048, 4096) on any CPU
    assert torch.all(all_bf16.float().remainder(16.0) == 0.0)
    assert torch.all(v16.remainder(16.0) != 0.0)
    assert (all_bf16.float() - v32).abs().max() >= 1.0
