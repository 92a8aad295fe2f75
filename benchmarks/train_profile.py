"""Where a training iteration's time goes: rollout simulation, rollout inference, the update, and
the update's operators (torch profiler, self CPU time).

    python benchmarks/train_profile.py [--method ours] [--track lemniscate] [--precision fp32] [--top 15]

One thread, the cpu preset, one warm-up iteration, then one timed iteration (the split) and one
profiled iteration (the operators of the update: everything after the rollout).
"""

from __future__ import annotations

import argparse
import json

import torch
from torch.profiler import ProfilerActivity, profile

from cfrace.rl.train import TrainConfig, make_env, pick_device, resolve_precision, set_threads
from cfrace.rl.runner import Runner


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--method", default="ours")
    p.add_argument("--track", default="lemniscate")
    p.add_argument("--precision", default="fp32")
    p.add_argument("--preset", default="cpu")
    p.add_argument("--envs", type=int, default=None)
    p.add_argument("--top", type=int, default=15)
    args = p.parse_args()
    cfg = TrainConfig(args.method, args.track, preset=args.preset, num_envs=args.envs, threads=1, minutes=1)
    dev = pick_device("cpu")
    set_threads(1, dev)
    env, _ = make_env(cfg, dev, cfg.ippo().num_envs)
    runner = Runner(env, cfg.ippo(), seed=0)
    runner.precision = resolve_precision(args.precision, runner)
    runner.iterate()
    m = runner.iterate()
    split = {k: m[k] / m["iter_s"] for k in ("sim_s", "infer_s", "update_s")}
    split["other"] = 1.0 - sum(split.values())
    print(json.dumps({"iter_s": m["iter_s"], "env_steps_per_s": m["fps"], "shares": split}, indent=1))
    rollout = runner._rollout_step
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        runner._rollout_step = lambda *a: None  # only the update below is profiled
        try:
            runner.iterate()
        finally:
            runner._rollout_step = rollout
    table = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.top)
    print(table)


if __name__ == "__main__":
    main()
