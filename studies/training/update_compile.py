"""torch.compile of the PPO minibatch step against eager: compile time and time per minibatch.

    python studies/training/update_compile.py [--method ours] [--precision fp32|bf16] [--steps 40] [--json FILE]

One agent's networks of the cpu preset, a minibatch of the preset's size (worlds x rollout /
minibatches), the step as cfrace/rl/ippo.py runs it (forward with the output layers in float32,
the PPO losses, backward, grad-norm clip, fused Adam); the compiled variant compiles forward +
losses + backward (``torch.compile`` of the loss function, dynamic shapes: the alive sample count
changes every iteration). One thread. Prints the compile time (first call; set TORCHINDUCTOR_CACHE_DIR to
an empty folder for a cold compile), the median time per minibatch of each, how many minibatches
the compile costs, and how far the compiled gradients are from the eager ones (relative, per tensor).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from cfrace.contract import MULTI_AGENT_METHODS
from cfrace.rl.config import preset
from cfrace.rl.ippo import forward, make_optimizer, ppo_losses
from cfrace.rl.models import AgentModels
from cfrace.rl.precision import Precision


def _setup(cfg, obs_dim: int, critic_dim: int, n: int, seed: int = 0):
    torch.manual_seed(seed)
    model = AgentModels(obs_dim, critic_dim, cfg.actor_hidden, cfg.critic_hidden, 1.0)
    obs, critic = torch.randn(n, obs_dim), torch.randn(n, critic_dim)
    with torch.no_grad():
        dist = model.actor(obs)
        actions = dist.sample()
        mb = {"actions": actions, "log_prob": dist.log_prob(actions).sum(-1), "values": model.critic(critic),
              "advantages": torch.randn(n), "returns": torch.randn(n)}
    return model, make_optimizer(model, cfg.lr), obs, critic, mb


def _grad_diff(eager, compiled, model, obs, critic, mb) -> tuple[float, float]:
    """Largest relative difference (norm) between the eager and the compiled gradients of one tensor,
    and the seconds of the compiled function's first call (the compilation)."""
    grads, first_s = [], 0.0
    for fn in (eager, compiled):
        model.zero_grad(set_to_none=True)
        t0 = time.perf_counter()
        fn(obs, critic, mb).backward()
        first_s = time.perf_counter() - t0
        grads.append([q.grad.clone() for q in model.parameters()])
    model.zero_grad(set_to_none=True)
    return max(float((a - b).norm() / a.norm().clamp_min(1e-12)) for a, b in zip(*grads)), first_s


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--method", default="ours")
    p.add_argument("--precision", default="fp32", choices=("fp32", "bf16"))
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--json")
    args = p.parse_args()
    torch.set_num_threads(1)
    multi = args.method in MULTI_AGENT_METHODS
    cfg = preset("cpu", multi)
    obs_dim, critic_dim = (42, 84) if multi else (42, 42)
    n = cfg.num_envs * cfg.rollout // cfg.minibatches
    prec = Precision(args.precision, args.precision, "asked")
    autocast = lambda: prec.autocast(torch.device("cpu"))
    model, opt, obs, critic, mb = _setup(cfg, obs_dim, critic_dim, n)
    params = [q for g in opt.param_groups for q in g["params"]]

    def loss_fn(obs, critic, mb):
        dist, value = forward(model, obs, critic, autocast)
        return ppo_losses(dist, value, mb, cfg)[0]

    compiled = torch.compile(loss_fn, dynamic=True)
    diff, compile_s = _grad_diff(loss_fn, compiled, model, obs, critic, mb)
    res = {"method": args.method, "precision": args.precision, "minibatch": n, "grad_rel_diff": diff,
           "compile_s": compile_s}
    for name, fn in (("eager", loss_fn), ("compiled", compiled)):
        times = []
        for i in range(args.steps + 1):  # the first (not counted) warms up
            t0 = time.perf_counter()
            loss = fn(obs, critic, mb)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
            opt.step()
            if i > 0:
                times.append(time.perf_counter() - t0)
        res[f"{name}_ms"] = 1e3 * statistics.median(times)
    res["speedup"] = res["eager_ms"] / res["compiled_ms"]
    saved_ms = res["eager_ms"] - res["compiled_ms"]
    res["minibatches_to_repay_compile"] = (compile_s * 1e3 / saved_ms) if saved_ms > 0 else None
    print(json.dumps(res, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
