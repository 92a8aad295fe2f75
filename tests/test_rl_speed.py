"""The trainer's speed options change how the update computes, never what it learns."""

from __future__ import annotations

import pytest
import torch

from cfrace.rl.config import preset
from cfrace.rl.runner import Runner

from toy_env import ToyRaceEnv

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _trained(workers: int, shared: bool = False, iterations: int = 2) -> tuple[Runner, list[dict]]:
    env = ToyRaceEnv(64, 2, episode_steps=10, seed=4)
    cfg = preset("cpu", True, (("shared", shared),), num_envs=64, rollout=8, actor_hidden=(32, 32),
                 critic_hidden=(32,), epochs=2, minibatches=2)
    runner = Runner(env, cfg, seed=4)
    runner.update_workers = workers
    return runner, [runner.iterate() for _ in range(iterations)]


def _same(a: Runner, b: Runner) -> None:
    for ma, mb in zip(a.agents, b.agents):
        for (name, x), y in zip(ma.state_dict().items(), mb.state_dict().values()):
            assert torch.equal(x, y), name
    for oa, ob in zip(a.optimizers, b.optimizers):
        for sa, sb in zip(oa.state.values(), ob.state.values()):
            assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert torch.equal(a.update_gen.get_state(), b.update_gen.get_state())


def test_agents_updated_in_threads_learn_the_same_weights():
    one, m1 = _trained(1)
    two, m2 = _trained(2)
    _same(one, two)
    timing = ("fps", "iter_s", "sim_s", "infer_s", "update_s")
    assert [{k: v for k, v in m.items() if k not in timing} for m in m1] == \
           [{k: v for k, v in m.items() if k not in timing} for m in m2]
    # the update moved the weights (the comparison is not between two untouched models)
    fresh = Runner(ToyRaceEnv(64, 2, episode_steps=10, seed=4), one.cfg, seed=4)
    assert not torch.equal(fresh.agents[0].actor.mean_net[0].weight, one.agents[0].actor.mean_net[0].weight)


def test_threads_with_one_shared_model_are_the_sequential_update():
    one, _ = _trained(1, shared=True, iterations=1)
    two, _ = _trained(2, shared=True, iterations=1)
    _same(one, two)


def test_compiled_loss_follows_the_eager_update(ppo_batch):
    """The compiled minibatch loss (traced by dynamo and AOT autograd; the aot_eager backend keeps the
    test fast, the inductor code generation is timed in studies/training/update_compile.py) moves the
    weights as the eager one, over minibatches of changing size."""
    from cfrace.rl.ippo import compiled_loss, make_optimizer, ppo_update

    from torch._dynamo.utils import counters

    cfg = preset("cpu", True, epochs=2, minibatches=3)
    counters.clear()
    runs = []
    for loss_fn in (None, compiled_loss("aot_eager")):
        model, batch = ppo_batch(n=600)
        opt = make_optimizer(model, cfg.lr)
        for n in (600, 450):  # the alive count changes between iterations
            part = {k: v[:n] for k, v in batch.items()}
            stats, _ = ppo_update(model, opt, part, cfg, cfg.lr, torch.Generator().manual_seed(n), None, None, loss_fn)
        runs.append((model, stats))
    (eager, s_eager), (comp, s_comp) = runs
    for (name, a), b in zip(eager.state_dict().items(), comp.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=name)
    assert s_comp == pytest.approx(s_eager, rel=1e-4, abs=1e-6)
    assert counters["stats"]["unique_graphs"] >= 1  # the compiled path ran
    start, _ = ppo_batch(n=600)
    assert not torch.equal(start.critic.net[0].weight, eager.critic.net[0].weight)


def test_bf16_training_exports_a_float32_onnx_that_passes_parity(tmp_path, monkeypatch):
    """After a bf16 training: float32 weights in the checkpoint, a float32 ONNX graph that matches the
    torch actor, and auto's choice (with its measured times) recorded in the checkpoint."""
    import onnx

    from cfrace.export import export_checkpoint
    from cfrace.rl import precision as prec
    from cfrace.rl.train import load_checkpoint, train
    from test_rl_train import _cfg, toy_factory

    res = train(_cfg(tmp_path, precision="bf16"), env_factory=toy_factory)
    assert res.precision.dtype == "bf16"
    ck = load_checkpoint(tmp_path / "run")
    assert ck["precision"]["dtype"] == "bf16"
    assert all(v.dtype == torch.float32 for agent in ck["runner"]["agents"] for k, v in agent.items()
               if v.is_floating_point() and "norm" not in k)
    path, _, err = export_checkpoint(tmp_path / "run", tmp_path / "bf16.onnx", "best")
    assert err < 1e-5
    graph = onnx.load(str(path)).graph
    f32 = onnx.TensorProto.FLOAT
    assert all(v.type.tensor_type.elem_type == f32 for v in [*graph.input, *graph.output])
    assert all(t.data_type == f32 for t in graph.initializer if t.data_type != onnx.TensorProto.INT64)

    monkeypatch.setattr(prec, "cpu_has_bf16", lambda: True)  # auto measures on any CPU then
    train(_cfg(tmp_path, precision="auto", out=str(tmp_path / "auto")), env_factory=toy_factory)
    rec = load_checkpoint(tmp_path / "auto")["precision"]
    assert rec["mode"] == "auto" and rec["fp32_ms"] > 0 and rec["bf16_ms"] > 0
    assert (rec["dtype"] == "bf16") == (rec["fp32_ms"] / rec["bf16_ms"] >= prec.MIN_GAIN)
