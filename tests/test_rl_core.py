"""IPPO pieces: GAE, the running normaliser, the PPO update, the runner on the toy env."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cfrace.rl.config import preset
from cfrace.rl.ippo import make_optimizer, ppo_loss, ppo_update
from cfrace.rl.models import AgentModels, RunningNorm
from cfrace.rl.runner import Runner
from cfrace.rl.storage import RolloutStorage, gae

from toy_env import ToyRaceEnv


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def naive_gae(r, v, d, last, gamma, lam):
    """Per-sequence scalar loop, written independently: for every start t, sum the discounted TD
    errors until the first done."""
    T = len(r)
    vals = list(v) + [last]
    adv = [0.0] * T
    for t in range(T):
        total, w = 0.0, 1.0
        for k in range(t, T):
            nxt = 0.0 if d[k] else vals[k + 1]
            delta = r[k] + gamma * nxt - vals[k]
            total += w * delta
            if d[k]:
                break
            w *= gamma * lam
        adv[t] = total
    return adv


def test_gae_matches_naive_loop():
    gen = torch.Generator().manual_seed(0)
    T, E, A = 13, 5, 2
    r = torch.randn(T, E, A, generator=gen)
    v = torch.randn(T, E, A, generator=gen)
    d = torch.rand(T, E, A, generator=gen) < 0.2
    last = torch.randn(E, A, generator=gen)
    adv, ret = gae(r, v, d, last, 0.99, 0.95)
    for e in range(E):
        for a in range(A):
            ref = naive_gae(r[:, e, a].tolist(), v[:, e, a].tolist(), d[:, e, a].tolist(), float(last[e, a]),
                            0.99, 0.95)
            np.testing.assert_allclose(adv[:, e, a].numpy(), ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(ret, adv + v)


def test_gae_dead_steps_and_truncation_bootstrap():
    """Hand-built sequence through the runner's rules: a crash (terminated), dead steps, a reset,
    then a time-limit truncation with bootstrap r += gamma V(final)."""
    g, lam = 0.9, 0.8
    #         t:   0     1     2(crash) 3(dead) 4(dead) 5     6(trunc) 7
    reward = [1.0, 0.5, -2.0, 0.0, 0.0, 1.0, 1.0, 0.3]
    value = [2.0, 1.0, 0.5, 9.0, 9.0, 1.5, 1.2, 0.7]
    term = [0, 0, 1, 0, 0, 0, 0, 0]
    trunc = [0, 0, 0, 0, 0, 0, 1, 0]
    alive = [1, 1, 1, 0, 0, 1, 1, 1]
    v_final, last = 4.0, 0.6
    r = torch.tensor(reward)
    r[6] += g * v_final
    done = torch.tensor([bool(a or b or not c) for a, b, c in zip(term, trunc, alive)])
    adv, _ = gae(r[:, None], torch.tensor(value)[:, None], done[:, None], torch.tensor([last]), g, lam)
    adv = adv[:, 0].tolist()
    # by hand
    a7 = 0.3 + g * last - 0.7
    a6 = 1.0 + g * v_final - 1.2          # chain cut at the truncation, bootstrapped from V(final)
    a5 = (1.0 + g * 1.2 - 1.5) + g * lam * a6
    a2 = -2.0 - 0.5                       # crash: no bootstrap
    a1 = (0.5 + g * 0.5 - 1.0) + g * lam * a2
    a0 = (1.0 + g * 1.0 - 2.0) + g * lam * a1
    np.testing.assert_allclose([adv[i] for i in (0, 1, 2, 5, 6, 7)], [a0, a1, a2, a5, a6, a7], rtol=1e-5)
    # dead steps are excluded from the batch
    st = RolloutStorage(8, 1, 1, 3, 3, "cpu")
    st.alive[:, 0, 0] = torch.tensor(alive, dtype=torch.bool)
    st.compute_returns(torch.zeros(1, 1), g, lam)
    assert st.agent_batch(0)["obs"].shape[0] == 6


def test_running_norm_matches_numpy():
    gen = torch.Generator().manual_seed(1)
    norm = RunningNorm(4)
    chunks = [torch.randn(n, 4, generator=gen) * torch.tensor([1.0, 10.0, 0.1, 3.0]) + torch.tensor([5.0, -2.0, 0, 1])
              for n in (1, 7, 300, 2, 1000)]
    for c in chunks:
        norm.update(c)
    allx = torch.cat(chunks).double().numpy()
    np.testing.assert_allclose(norm.mean.numpy(), allx.mean(0), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(norm.var.numpy(), allx.var(0), rtol=1e-10)
    assert float(norm.count) == len(allx)
    y = norm(torch.from_numpy(allx).float())
    assert y.abs().max() <= 10.0
    np.testing.assert_allclose(y.mean(0).numpy(), 0.0, atol=1e-4)
    big = norm(torch.full((1, 4), 1e6))
    assert torch.all(big == 10.0)


@pytest.mark.parametrize("adaptive", [False, True])
def test_ppo_update_reduces_loss(adaptive, ppo_batch):
    cfg = preset("cpu", multi_agent=not adaptive, value_clip=None, epochs=8, minibatches=4)
    model, batch = ppo_batch()
    before = ppo_loss(model, batch, cfg)
    mean_before = model.actor(model.obs_norm(batch["obs"])).mean[:, 0].mean().item()
    opt = make_optimizer(model, cfg.lr)
    stats, lr = ppo_update(model, opt, batch, cfg, cfg.lr, torch.Generator().manual_seed(0))
    after = ppo_loss(model, batch, cfg)
    assert after < before - 0.1, (before, after)
    assert model.actor(model.obs_norm(batch["obs"])).mean[:, 0].mean().item() > mean_before  # moved toward A > 0
    assert stats["kl"] > 0 and stats["samples"] == 512
    if adaptive:
        assert lr != cfg.lr  # the KL rule changed the learning rate
        assert opt.param_groups[0]["lr"] == lr


def test_value_clip_limits_value_change(ppo_batch):
    cfg = preset("cpu", multi_agent=True, value_clip=0.2, lr=1e-2, epochs=5)
    model, batch = ppo_batch()
    batch["returns"] = batch["values"] + 100.0  # far away targets
    ppo_update(model, make_optimizer(model, cfg.lr), batch, cfg, cfg.lr, torch.Generator().manual_seed(0))
    with torch.no_grad():
        v = model.critic(model.critic_norm(batch["critic"]))
    # with value clipping the loss gives no gradient once a value is 0.2 past the old one (only Adam momentum)
    assert (v - batch["values"]).abs().mean() < 1.5


def test_runner_iteration_on_toy_env():
    env = ToyRaceEnv(64, 2, episode_steps=10, seed=0)
    cfg = preset("cpu", multi_agent=True, num_envs=64, rollout=16, actor_hidden=(16,), critic_hidden=(16,))
    runner = Runner(env, cfg, seed=0)
    m = runner.iterate()
    assert m["env_steps"] == 64 * 16 and m["iteration"] == 1
    assert 0 < m["alive_agent0"] <= 1 and m["alive_agent0"] < 1  # some crashes / dead steps happened
    assert np.isfinite(m["return_agent1"]) and "term_progress_agent0" in m and "stat_success" in m
    assert runner.agents[0].obs_norm.count > 64  # warm start + rollout
    assert m["sim_s"] > 0 and m["update_s"] > 0 and m["infer_s"] > 0
    # the agents are independent: different initial weights, separate optimizers
    w0, w1 = (a.actor.mean_net[0].weight for a in runner.agents)
    assert not torch.equal(w0, w1)


def test_runner_can_keep_the_actor_input_statistics_fixed():
    """Warm starts keep the source actor's normaliser (cfrace/rl/train.py sets the flag from --init-from)."""
    env = ToyRaceEnv(64, 2, episode_steps=10, seed=0)
    cfg = preset("cpu", multi_agent=True, num_envs=64, rollout=16, actor_hidden=(16,), critic_hidden=(16,))
    runner = Runner(env, cfg, seed=0)
    runner.update_actor_norm = False
    before = [(a.obs_norm.mean.clone(), a.obs_norm.count.clone(), a.critic_norm.count.clone()) for a in runner.agents]
    runner.iterate()
    for a, (mean, count, ccount) in zip(runner.agents, before):
        assert torch.equal(a.obs_norm.mean, mean) and torch.equal(a.obs_norm.count, count)
        assert a.critic_norm.count > ccount          # the fresh critics' statistics still follow the task


@pytest.mark.slow
def test_runner_learns_on_toy_env():
    env = ToyRaceEnv(256, 2, episode_steps=30, seed=3)
    cfg = preset("cpu", multi_agent=True, num_envs=256, rollout=16, actor_hidden=(64, 64), critic_hidden=(64, 64),
                 lr=1e-3)
    runner = Runner(env, cfg, seed=3)
    first = [runner.iterate() for _ in range(3)]
    for _ in range(9):
        last = runner.iterate()
    r0 = np.mean([m["reward_agent0"] + m["reward_agent1"] for m in first])
    r1 = last["reward_agent0"] + last["reward_agent1"]
    assert r1 > r0 + 0.15, (r0, r1)  # random policy about -0.05, learnt about +0.3 per step
    assert last["stat_success"] > 0.8


def test_resume_is_exact(tmp_path):
    """Save after 2 iterations, restore into fresh objects: the 3rd iteration is bit-identical."""
    def make():
        env = ToyRaceEnv(32, 2, episode_steps=7, seed=5)
        cfg = preset("cpu", multi_agent=True, num_envs=32, rollout=8, actor_hidden=(16,), critic_hidden=(16,),
                     desired_kl=0.01)
        return Runner(env, cfg, seed=5)

    a = make()
    a.iterate()
    a.iterate()
    torch.save(a.state_dict(), tmp_path / "ck.pt")
    ma = a.iterate()
    torch.manual_seed(123)  # disturb the global RNG: the checkpoint must restore it
    b = make()
    assert b.load_state_dict(torch.load(tmp_path / "ck.pt", weights_only=False)) is True
    mb = b.iterate()
    for k, v in ma.items():
        if k.endswith("_s") or k == "fps":
            continue
        assert (np.isnan(v) and np.isnan(mb[k])) or v == mb[k], k
    for pa, pb in zip(a.agents.state_dict().values(), b.agents.state_dict().values()):
        assert torch.equal(pa, pb)
    assert torch.equal(a.obs, b.obs) and a.lrs == b.lrs and a.env_steps == b.env_steps == 3 * 32 * 8


def test_presets_and_overrides():
    from cfrace.errors import ConfigError
    from cfrace.rl.config import parse_overrides

    paper_ma, paper_sa = preset("paper", True), preset("paper", False)
    assert paper_ma.actor_hidden == (512, 512, 256, 128) and paper_ma.critic_hidden == (512, 512, 256, 256, 128, 128)
    assert (paper_ma.num_envs, paper_ma.rollout, paper_ma.lr, paper_ma.desired_kl, paper_ma.grad_clip) == \
        (10240, 16, 1e-4, None, 0.5)
    assert (paper_sa.rollout, paper_sa.lr, paper_sa.desired_kl, paper_sa.grad_clip) == (24, 5e-4, 0.01, 1.0)
    ov = parse_overrides(["epochs=3", "actor_hidden=[64, 32]", "value_clip=none", "lr=2e-4"])
    cfg = preset("paper", True, ov, num_envs=64)
    assert (cfg.epochs, cfg.actor_hidden, cfg.value_clip, cfg.lr, cfg.num_envs) == (3, (64, 32), None, 2e-4, 64)
    for bad in (["nope=1"], ["epochs"], ["preset=cpu"], ["epochs=2.5"], ["actor_hidden=64"], ["lr=fast"]):
        with pytest.raises(ConfigError):
            parse_overrides(bad)
    with pytest.raises(ConfigError):
        preset("gpu", True)
