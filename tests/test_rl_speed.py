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
