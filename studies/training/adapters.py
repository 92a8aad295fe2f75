"""Cost of the Gymnasium / PettingZoo adapters over the native batched RaceEnv, at equal world counts.

    .venv/bin/python studies/training/adapters.py [--worlds 1,16,256] [--seconds 2] [--json FILE]

For each world count N, world-steps per second (one 50 Hz step of one world, all its drones) of:
  native ds     RaceEnv(N worlds, ds), torch actions
  vector ds     RaceVectorEnv(N) (gymnasium.vector.VectorEnv over the same RaceEnv), NumPy actions
  N x gym ds    N RaceGymEnv (one world each), stepped one after another (what SyncVectorEnv does)
  native ours   RaceEnv(N worlds, ours: 2 drones)
  vector ours   RaceParallelVectorEnv(N) (PettingZoo's dict API, values batched over the worlds)
  N x pz ours   N RaceParallelEnv (one world each, dict API), one after another
Uniform random actions in [-1, 1] (drones crash and worlds reset often, as early in training).
One thread; records the machine's load. Prints a markdown table and one JSON document.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np
import torch


def _rate(step, seconds: float) -> float:
    """Calls of step() per second over about ``seconds`` (after 5 warm-up calls)."""
    for _ in range(5):
        step()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        step()
        n += 1
    return n / (time.perf_counter() - t0)


def measure(n: int, seconds: float, per_env_max: int, repeats: int = 3) -> dict:
    """World-steps/s of every form at ``n`` worlds: the forms take turns, ``repeats`` rounds of
    ``seconds`` / ``repeats`` each, and the best round counts (the machine is shared: load only
    slows a form down, so the best round is the least disturbed)."""
    from cfrace.rl.adapters import make_race_env
    from cfrace.rl.adapters.gymnasium_env import RaceGymEnv, RaceVectorEnv
    from cfrace.rl.adapters.pettingzoo_env import RaceParallelEnv, RaceParallelVectorEnv

    rng = np.random.default_rng(0)
    act = rng.uniform(-1, 1, (n, 4)).astype(np.float32)
    act2 = rng.uniform(-1, 1, (n, 2, 4)).astype(np.float32)
    native, _ = make_race_env("ds", num_envs=n)
    native.reset()
    native2, _ = make_race_env("ours", num_envs=n)
    native2.reset()
    venv = RaceVectorEnv(n, "ds")
    venv.reset(seed=0)
    pvec = RaceParallelVectorEnv(n, "ours")
    pvec.reset(seed=0)
    act_t, act2_t = torch.as_tensor(act).reshape(n, 1, 4), torch.as_tensor(act2)
    act_d = {a: act2[:, k] for k, a in enumerate(pvec.agents)}
    forms = {"native_ds": lambda: native.step(act_t), "vector_ds": lambda: venv.step(act),
             "native_ours": lambda: native2.step(act2_t), "vector_pz_ours": lambda: pvec.step(act_d)}
    if n <= per_env_max:
        envs = [RaceGymEnv("ds", seed=i) for i in range(n)]
        pzs = [RaceParallelEnv("ours", seed=i) for i in range(n)]
        for e in envs:
            e.reset(seed=0)
        for p in pzs:
            p.reset(seed=0)

        def gym_step():
            for i, e in enumerate(envs):
                _, _, term, trunc, _ = e.step(act[i])
                if term or trunc:
                    e.reset()

        def pz_step():
            for i, p in enumerate(pzs):
                p.step({a: act2[i, k] for k, a in enumerate(p.agents)})
                if not p.agents:
                    p.reset()

        forms.update(per_env_gym_ds=gym_step, per_env_pz_ours=pz_step)
    out = {"worlds": n, **{k: 0.0 for k in forms}}
    for _ in range(repeats):
        for k, step in forms.items():
            out[k] = max(out[k], n * _rate(step, seconds / repeats))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", default="1,16,256")
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--per-env-max", type=int, default=256, help="largest N for the one-world-per-env forms")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    rows = [measure(int(n), args.seconds, args.per_env_max) for n in args.worlds.split(",")]
    doc = {"rows": rows, "load_before": load_before, "load_after": os.getloadavg(), "cpu_count": os.cpu_count(),
           "torch_threads": 1, "unit": "world-steps per second"}
    cols = ("native_ds", "vector_ds", "per_env_gym_ds", "native_ours", "vector_pz_ours", "per_env_pz_ours")
    ratios = (("vector_ds", "native_ds"), ("per_env_gym_ds", "native_ds"), ("vector_pz_ours", "native_ours"),
              ("per_env_pz_ours", "native_ours"))
    print("| worlds | " + " | ".join(cols) + " | " + " | ".join(f"{a} / {b}" for a, b in ratios) + " |")
    print("|---" * (1 + len(cols) + len(ratios)) + "|")
    for r in rows:
        cells = [f"{r[c]:,.0f}" if c in r else "-" for c in cols]
        cells += [f"{r[a] / r[b]:.2f}" if a in r else "-" for a, b in ratios]
        print(f"| {r['worlds']} | " + " | ".join(cells) + " |")
    print(f"load average before {load_before}, after {doc['load_after']}", file=sys.stderr)
    text = json.dumps(doc, indent=2)
    if args.json:
        with open(args.json, "w") as fh:
            fh.write(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
