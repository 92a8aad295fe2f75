"""The training loop (budgets, logs, checkpoints, resume, signals) and checkpoint export, on the toy env."""

from __future__ import annotations

import csv
import os
import signal

import numpy as np
import pytest
import torch

from cfrace.drone import load_profile
from cfrace.errors import ConfigError, PolicyError
from cfrace.export import export_checkpoint
from cfrace.policy import OnnxPolicy
from cfrace.rl.train import TrainConfig, bench_train, env_meta, load_checkpoint, resume_config, train

from toy_env import ToyRaceEnv


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def toy_factory(cfg, device, num_envs):
    layout = {("ours", False): "race42", ("ds", False): "solo36"}[(cfg.method, cfg.obstacles)]
    env = ToyRaceEnv(num_envs, 2 if cfg.method == "ours" else 1, episode_steps=12, seed=cfg.seed, layout=layout)
    return env, env_meta(cfg, env, "complex", load_profile(cfg.profile))


def _cfg(tmp_path, **kw):
    base = dict(method="ours", track="complex", num_envs=16, steps=16 * 16 * 3, out=str(tmp_path / "run"),
                device="cpu", threads=1, seed=2)
    base.update(kw)
    return TrainConfig(**base)


def _spy_actions(env) -> dict:
    """Make env.step record the actions it was last given (seen["a"], (E, A, 4))."""
    seen, step = {}, env.step

    def spy(actions):
        seen["a"] = actions.clone()
        return step(actions)

    env.step = spy
    return seen


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_train_writes_outputs_and_resumes_exactly(tmp_path):
    # uninterrupted: 5 iterations
    full = train(_cfg(tmp_path, steps=16 * 16 * 5, out=str(tmp_path / "full")), env_factory=toy_factory)
    assert full.iterations == 5 and not full.interrupted
    # interrupted after 3, resumed to 5
    part = train(_cfg(tmp_path, steps=16 * 16 * 3), env_factory=toy_factory)
    assert part.iterations == 3 and part.env_steps == 16 * 16 * 3
    out = tmp_path / "run"
    for name in ("checkpoint.pt", "metrics.csv", "training_curve.png"):
        assert (out / name).stat().st_size > 0
    assert (out / "training_curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert list((out / "tb").glob("events.out.tfevents.*"))
    ck = load_checkpoint(out)
    assert ck["meta"]["obs_layout"] == "race42" and ck["runner"]["iteration"] == 3
    cfg = resume_config(out, steps=16 * 16 * 5, device="cpu", threads=1)
    assert cfg.method == "ours" and cfg.seed == 2 and cfg.out == str(out)
    res = train(cfg, resume=out, env_factory=toy_factory)
    assert res.exact_resume is True and res.iterations == 5
    a, b = _rows(tmp_path / "full" / "metrics.csv"), _rows(out / "metrics.csv")
    assert [r["iteration"] for r in b] == ["1", "2", "3", "4", "5"]
    for ra, rb in zip(a, b):  # same numbers as without the interruption
        for k in ra:
            if not (k.endswith("_s") or k == "fps"):
                assert ra[k] == rb[k], (ra["iteration"], k)
    wa = load_checkpoint(tmp_path / "full")["runner"]["agents"]
    wb = load_checkpoint(out)["runner"]["agents"]
    for sa, sb in zip(wa, wb):
        for k in sa:
            assert torch.equal(sa[k], sb[k]), k


def test_resume_refuses_other_task(tmp_path):
    train(_cfg(tmp_path, steps=16 * 16), env_factory=toy_factory)
    with pytest.raises(ConfigError, match="method"):
        resume_config(tmp_path / "run", method="ds")
    with pytest.raises(ConfigError):
        load_checkpoint(tmp_path / "nowhere")
    for name, data in (("junk.pt", b"garbage"), ("empty.pt", b""), ("zeros.pt", bytes(100)), ("text.pt", b"hello")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(ConfigError, match="not a cfrace training checkpoint"):
            load_checkpoint(tmp_path / name)
    import zipfile                                # a zip, but no checkpoint: the message says what torch said
    with zipfile.ZipFile(tmp_path / "other.zip", "w") as z:
        z.writestr("a.txt", "x")
    with pytest.raises(ConfigError, match="not a readable checkpoint"):
        load_checkpoint(tmp_path / "other.zip")


def test_signal_checkpoints_and_stops(tmp_path):
    seen = []
    before = signal.getsignal(signal.SIGINT)   # default_int_handler, or SIG_IGN in a background job

    def on_iteration(metrics, info):
        seen.append(metrics["iteration"])
        if metrics["iteration"] == 2:
            os.kill(os.getpid(), signal.SIGINT)  # like Ctrl-C: finish the iteration, checkpoint, stop

    res = train(_cfg(tmp_path, steps=None, minutes=5.0), env_factory=toy_factory, on_iteration=on_iteration)
    assert res.interrupted and res.iterations == 2 and seen == [1, 2]
    assert load_checkpoint(tmp_path / "run")["runner"]["iteration"] == 2
    assert signal.getsignal(signal.SIGINT) is before  # handler restored


def test_export_agents_from_checkpoint(tmp_path):
    train(_cfg(tmp_path), env_factory=toy_factory)
    ck = load_checkpoint(tmp_path / "run")
    totals = [float(v) for v in ck["runner"]["total_reward"]]
    best = int(np.argmax(totals))
    paths = {}
    for agent in ("ego", "adversary", "best"):
        path, meta, err = export_checkpoint(tmp_path / "run", tmp_path / f"{agent}.onnx", agent)
        assert err < 1e-5
        paths[agent] = path
        pol = OnnxPolicy(path)
        assert pol.meta["method"] == "ours" and pol.meta["obs_dim"] == 42 and pol.meta["track"] == "complex"
        assert pol.meta["train_steps"] == 16 * 16 * 3 and pol.meta["seed"] == 2
        assert pol.meta["agent"] == ("ego", "adversary")[best] if agent == "best" else pol.meta["agent"] == agent
    obs = np.random.default_rng(0).normal(size=(50, 42)).astype(np.float32)
    ego, adv, bst = (OnnxPolicy(paths[k])(obs) for k in ("ego", "adversary", "best"))
    assert np.abs(ego - adv).max() > 1e-4  # two different actors
    np.testing.assert_array_equal(bst, (ego, adv)[best])
    with pytest.raises(PolicyError):
        export_checkpoint(tmp_path / "run", tmp_path / "x.onnx", "nobody")


def test_export_single_agent_refuses_adversary(tmp_path):
    train(_cfg(tmp_path, method="ds", steps=16 * 24), env_factory=toy_factory)
    path, meta, _ = export_checkpoint(tmp_path / "run", tmp_path / "ds.onnx", "best")
    assert OnnxPolicy(path).meta["obs_layout"] == "solo36" and meta["agent"] == "ego"
    with pytest.raises(PolicyError, match="single-agent"):
        export_checkpoint(tmp_path / "run", tmp_path / "x.onnx", "adversary")


def test_bench_train_split(tmp_path):
    r = bench_train("ours", "complex", num_envs=16, iterations=2, device="cpu", threads=1, env_factory=toy_factory)
    assert r["env_steps_per_s"] > 0 and r["num_agents"] == 2
    total = r["share_sim"] + r["share_inference"] + r["share_update"] + r["share_other"]
    assert abs(total - 1.0) < 1e-9 and r["share_update"] > 0 and r["share_sim"] > 0


def test_critic_warmup_trains_only_the_critics_at_their_own_rate(tmp_path):
    """After --init-from the actors stay frozen for critic_warmup iterations while the critics train
    at critic_warmup_lr; then every agent returns to the preset's rate and the actors move."""
    src = train(_cfg(tmp_path, method="ds", steps=16 * 24 * 2, out=str(tmp_path / "src")), env_factory=toy_factory)
    seen = []

    def on_iteration(metrics, info):
        seen.append(metrics)

    cfg = _cfg(tmp_path, steps=16 * 16 * 5, out=str(tmp_path / "warm"), init_from=str(src.checkpoint),
               critic_warmup=3, critic_warmup_lr=2e-3)
    res = train(cfg, env_factory=toy_factory, on_iteration=on_iteration)
    lrs = [m["lr_agent0"] for m in seen]
    assert lrs[:3] == [2e-3] * 3 and lrs[3] == pytest.approx(cfg.ippo().lr)
    kls = [m["kl_agent0"] for m in seen]
    assert all(k == 0.0 for k in kls[:3]) and kls[3] > 0.0     # frozen actors, then moving ones
    assert res.iterations == 5


def test_init_critic_copies_a_fitting_critic_and_refuses_another(tmp_path):
    from cfrace.rl.warmstart import warm_start
    import types

    src = train(_cfg(tmp_path, method="ds", steps=16 * 24, out=str(tmp_path / "src")), env_factory=toy_factory)
    saved = load_checkpoint(src.checkpoint)["runner"]["agents"][0]
    from cfrace.rl.models import AgentModels
    from cfrace.rl.config import preset

    p = preset("cpu", multi_agent=False)
    solo = AgentModels(36, 36, p.actor_hidden, p.critic_hidden, 1.0)
    warm_start(types.SimpleNamespace(agents=[solo]), src.checkpoint, "solo36", critic=True)
    for k, v in saved.items():
        if k.startswith("critic"):
            assert torch.equal(solo.state_dict()[k], v), k
    # into a racer: the source critic reads the own observation's first 36 inputs, the rest start at 0
    race = AgentModels(42, 84, p.actor_hidden, p.critic_hidden, 1.0)
    warm_start(types.SimpleNamespace(agents=[race]), src.checkpoint, "race42", critic=True)
    x = torch.randn(32, 84) * 2
    with torch.no_grad():
        want = solo.critic(solo.critic_norm(x[:, :36]))
        got = race.critic(race.critic_norm(x))
    assert torch.allclose(got, want, atol=1e-5)
    assert torch.equal(race.critic_norm.mean[42:78], saved["critic_norm.mean"])
    wide = AgentModels(42, 84, p.actor_hidden, (64,), 1.0)
    with pytest.raises(ConfigError, match="does not fit"):
        warm_start(types.SimpleNamespace(agents=[wide]), src.checkpoint, "race42", critic=True)


def test_fixed_opponent_flies_the_second_slot_in_part_of_the_worlds(tmp_path):
    """--fixed-opponent: in the first half of the worlds the second drone is flown by the frozen
    source actor (mean action); those samples are not agent 1's (out of its batch), agent 0 learns
    from all worlds."""
    from cfrace.rl.runner import Runner
    from cfrace.rl.train import _fixed_opponent

    src = train(_cfg(tmp_path, method="ds", steps=16 * 24, out=str(tmp_path / "src")), env_factory=toy_factory)
    cfg = _cfg(tmp_path, fixed_opponent=str(src.checkpoint), fixed_opponent_frac=0.5)
    env, meta = toy_factory(cfg, "cpu", 16)
    runner = Runner(env, cfg.ippo(), seed=0)
    info = _fixed_opponent(runner, cfg, meta["obs_layout"])
    assert info["fixed_opponent_worlds"] == 8
    seen = _spy_actions(env)
    obs = runner.obs.clone()
    runner.iterate()
    fo = runner.fixed_opponent
    first = seen  # the last step's actions: fixed slots hold the opponent's mean action
    st = runner.storage
    assert not st.alive[:, :8, 1].any()                    # fixed slots: never agent 1's samples
    assert st.alive[:, 8:, 1].any() and st.alive[:, :, 0].any()
    with torch.no_grad():
        want = fo.actor(fo.obs_norm(st.obs[-1, :8, 1])).mean
    assert torch.allclose(first["a"][:8, 1], want.clamp(-10, 10), atol=1e-6)
    assert not torch.allclose(first["a"][8:, 1], fo.actor(fo.obs_norm(st.obs[-1, 8:, 1])).mean.detach())
    assert obs.shape == runner.obs.shape
    # end to end: the run trains, and the exported actor says what it was trained against
    res = train(_cfg(tmp_path, steps=16 * 16 * 2, out=str(tmp_path / "fo"), fixed_opponent=str(src.checkpoint)),
                env_factory=toy_factory)
    path, _, _ = export_checkpoint(res.checkpoint, tmp_path / "fo.onnx", "ego")
    onnx_meta = OnnxPolicy(path).meta
    assert onnx_meta["fixed_opponent"] == "src" and onnx_meta["fixed_opponent_worlds"] == 8
    with pytest.raises(ConfigError, match="multi-agent"):
        ds_cfg = _cfg(tmp_path, method="ds", fixed_opponent=str(src.checkpoint))
        ds_env, ds_meta = toy_factory(ds_cfg, "cpu", 16)
        _fixed_opponent(Runner(ds_env, ds_cfg.ippo(), seed=0), ds_cfg, ds_meta["obs_layout"])


def test_resume_with_a_fixed_opponent_is_exact(tmp_path):
    """Loading the frozen opponent draws from torch's RNG: on --resume it happens before the saved RNG
    states are put back, so 3 + 2 iterations give the numbers of 5 uninterrupted ones."""
    src = train(_cfg(tmp_path, method="ds", steps=16 * 24, out=str(tmp_path / "src")), env_factory=toy_factory)
    kw = dict(fixed_opponent=f"{src.checkpoint},{src.checkpoint}", fixed_opponent_frac=1.0)
    train(_cfg(tmp_path, steps=16 * 16 * 5, out=str(tmp_path / "full"), **kw), env_factory=toy_factory)
    train(_cfg(tmp_path, steps=16 * 16 * 3, **kw), env_factory=toy_factory)
    res = train(resume_config(tmp_path / "run", steps=16 * 16 * 5, device="cpu", threads=1), resume=tmp_path / "run",
                env_factory=toy_factory)
    assert res.exact_resume is True and res.iterations == 5
    a, b = _rows(tmp_path / "full" / "metrics.csv"), _rows(tmp_path / "run" / "metrics.csv")
    assert [ra["reward_agent0"] for ra in a] == [rb["reward_agent0"] for rb in b]
    wa = load_checkpoint(tmp_path / "full")["runner"]["agents"]
    wb = load_checkpoint(tmp_path / "run")["runner"]["agents"]
    assert all(torch.equal(sa[k], sb[k]) for sa, sb in zip(wa, wb) for k in sa)

def test_fixed_opponent_flies_the_last_drones_of_a_field_with_a_shared_learner(tmp_path):
    """--fixed-opponent-drones 2 in 4-drone worlds: in the fixed worlds the last two drones fly the
    frozen actor's mean action and are out of the (shared) learner's samples; the first two learn in
    every world; all four learn elsewhere. At least one drone must learn."""
    from cfrace.rl.runner import Runner
    from cfrace.rl.train import _fixed_opponent

    src = train(_cfg(tmp_path, method="ds", steps=16 * 24, out=str(tmp_path / "src")), env_factory=toy_factory)
    cfg = _cfg(tmp_path, fixed_opponent=str(src.checkpoint), fixed_opponent_frac=0.5, fixed_opponent_drones=2,
               overrides=(("shared", True),))
    env = ToyRaceEnv(16, 4, episode_steps=12, seed=2, layout="race42")
    runner = Runner(env, cfg.ippo(), seed=0)
    assert len(runner.agents) == 1
    info = _fixed_opponent(runner, cfg, "race42")
    assert info == {"fixed_opponent": info["fixed_opponent"], "fixed_opponent_worlds": 8, "fixed_opponent_drones": 2}
    seen = _spy_actions(env)
    runner.iterate()
    st, fo = runner.storage, runner.fixed_opponent
    assert not st.alive[:, :8, 2:].any() and st.alive[:, 8:, 2:].any() and st.alive[:, :, :2].any()
    with torch.no_grad():
        want = fo.actor(fo.obs_norm(st.obs[-1, :8, 2:])).mean
        learner = fo.actor(fo.obs_norm(st.obs[-1, :8, :2])).mean
    assert torch.allclose(seen["a"][:8, 2:], want, atol=1e-6)
    assert not torch.allclose(seen["a"][:8, :2], learner)
    for k in (0, 4):
        with pytest.raises(ConfigError, match="--fixed-opponent-drones"):
            _fixed_opponent(Runner(env, cfg.ippo(), seed=0),
                            _cfg(tmp_path, fixed_opponent=str(src.checkpoint), fixed_opponent_drones=k), "race42")


def test_several_fixed_opponents_take_turns_by_world(tmp_path):
    """--fixed-opponent A,B: the fixed worlds are flown by A and B in turn (world i by the i % 2-th),
    and the exported metadata names both."""
    from cfrace.rl.runner import Runner
    from cfrace.rl.train import _fixed_opponent

    srcs = [train(_cfg(tmp_path, method="ds", steps=16 * 24, seed=s, out=str(tmp_path / f"src{s}")),
                  env_factory=toy_factory).checkpoint for s in (1, 2)]
    cfg = _cfg(tmp_path, fixed_opponent=f"{srcs[0]},{srcs[1]}", fixed_opponent_frac=0.75)
    env, meta = toy_factory(cfg, "cpu", 16)
    runner = Runner(env, cfg.ippo(), seed=0)
    assert _fixed_opponent(runner, cfg, meta["obs_layout"])["fixed_opponent_worlds"] == 12
    seen = _spy_actions(env)
    runner.iterate()
    obs = runner.storage.obs[-1, :, 1]
    with torch.no_grad():
        means = [fo.actor(fo.obs_norm(obs)).mean for fo in runner.fixed_opponents]
    assert not torch.allclose(means[0], means[1])
    for w in range(16):
        got = seen["a"][w, 1]
        assert torch.allclose(got, means[w % 2][w], atol=1e-6) == (w < 12)
    res = train(_cfg(tmp_path, steps=16 * 16, out=str(tmp_path / "two"), fixed_opponent=f"{srcs[0]},{srcs[1]}"),
                env_factory=toy_factory)
    path, _, _ = export_checkpoint(res.checkpoint, tmp_path / "two.onnx", "ego")
    assert OnnxPolicy(path).meta["fixed_opponent"] == "src1,src2"
