"""How much exploration noise does racing the track survive? A shipped policy that flies it, with noise.

    .venv/bin/python studies/training/noise_tolerance.py [--policy ss] [--track lemniscate] [--envs 256]
                                                   [--seconds 20] [--seed 1] [--sigmas 0,0.1,0.3,0.5,1]
                                                   [--dims 0123]

A training rollout does not fly the actor's mean action: it samples a ~ N(mu(o), sigma^2) per
action dimension (the environment then clips a to [-1, 1]), and a fresh actor starts at sigma =
init_std (1.0 in both presets). Here a policy that races the track (its exported mean action, which
the ONNX graph clips to [-1, 1]) flies the training environment (domain randomisation on, the
track's start mix: gate starts at rest and ground starts) with Gaussian noise of std sigma added to
each action, as a sampled rollout with that std would. Per sigma, over all worlds and the whole
window (auto-reset as in training; ``--dims``: only those action dimensions get noise, 0 = thrust,
1-3 = roll, pitch, yaw rate): the mean time between crashes (s of flight per crash), gates
per second and laps per minute of flight (counted by the sparse scheme's gate and lap terms). One
seed, nothing chosen: a property of the task, not of a training run.
"""

from __future__ import annotations

import argparse

import torch


def fly(policy_path: str, track_name: str, sigma: float, envs: int, seconds: float, seed: int,
        dims: str = "0123") -> dict:
    from cfrace.contract import POLICY_DT
    from cfrace.drone import load_profile
    from cfrace.env.race_env import RaceEnv
    from cfrace.policy import OnnxPolicy
    from cfrace.track import load_track

    policy = OnnxPolicy(policy_path)
    policy.check(track_name, False)
    env = RaceEnv(load_track(track_name), load_profile(policy.meta["drone_profile"]), num_envs=envs, method="ss",
                  obstacles=False, seed=seed, randomize=True)
    obs, _ = env.reset()
    gen = torch.Generator().manual_seed(seed + 1)
    mask = torch.tensor([float(str(k) in dims) for k in range(4)])
    alive_s = crashes = gates = laps = 0.0
    for _ in range(int(round(seconds / POLICY_DT))):
        mean = torch.from_numpy(policy(obs.reshape(-1, obs.shape[-1]).numpy())).reshape(envs, 1, 4)
        res = env.step(mean + sigma * mask * torch.randn(mean.shape, generator=gen))
        alive_s += float(res.alive.sum()) * POLICY_DT
        crashes += float(res.terminated.sum())
        gates += float(res.terms["gate"].sum()) / env.scales.gate_lead
        laps += float(res.terms["lap"].sum()) / env.scales.lap
        obs = res.obs
    return {"sigma": sigma, "s_per_crash": alive_s / max(crashes, 1.0), "gates_per_s": gates / alive_s,
            "laps_per_min": 60.0 * laps / alive_s, "flight_s": alive_s, "crashes": int(crashes)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", default="ss", help="shipped short name (ss, ds) or an ONNX path")
    ap.add_argument("--track", default="lemniscate")
    ap.add_argument("--envs", type=int, default=256)
    ap.add_argument("--seconds", type=float, default=20.0, help="s of simulated time per sigma")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--sigmas", default="0,0.1,0.2,0.3,0.5,0.7,1.0")
    ap.add_argument("--dims", default="0123", help="the action dimensions that get noise (0 thrust, 1-3 rates)")
    args = ap.parse_args()
    from cfrace.policy import resolve_policy

    torch.set_num_threads(1)
    path = str(resolve_policy(args.policy, args.track, False))
    print(f"{args.policy} on {args.track}: {args.envs} worlds x {args.seconds:g} s per sigma, seed {args.seed}, "
          f"noise on action dimensions {args.dims}")
    print("| action noise std | s of flight per crash | gates/s | laps/min |")
    print("|---|---|---|---|")
    for sigma in (float(x) for x in args.sigmas.split(",")):
        r = fly(path, args.track, sigma, args.envs, args.seconds, args.seed, args.dims)
        print(f"| {sigma:g} | {r['s_per_crash']:.2f} | {r['gates_per_s']:.2f} | {r['laps_per_min']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
