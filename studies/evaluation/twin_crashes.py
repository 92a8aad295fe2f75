"""When and where two copies of one policy crash into each other in a field, and how far the
policy's mean actions reach beyond the action range (what the action-bound loss would pull in).

    .venv/bin/python studies/evaluation/twin_crashes.py [--policy ours] [--field ours,ours,ds,ds] [--races 50] [--seed 100]
                                                [--track lemniscate]

Prints, for the field (cfrace.evaluate.field.race_field, gate starts, 3 laps): the crashes of the
policy's drones in contact with another copy of it, their times (s from the start) and gates passed
at the crash; then the share of the policy's mean actions (its torch copy read back from the ONNX
file, before the clamp) beyond +-1 per action, over 64 worlds x 500 steps of two copies racing.
"""

from __future__ import annotations

import argparse
import types

import numpy as np
import torch


def twin_crashes(policy: str, field: list[str], races: int, seed: int, track: str) -> dict:
    """Crashes of ``policy``'s drones touching another of its drones: count, times, gates passed."""
    from cfrace.evaluate.field import race_field

    r = race_field(track, field, races=races, seed=seed)
    rec, mine = r.recording, [k for k, x in enumerate(field) if x == policy]
    times, gates = [], []
    for w in range(r.races):
        for d in mine:
            steps = np.nonzero(rec.crashed_now[:, w, d])[0]
            if len(steps) and r.crash_partner[w, d] in mine:
                times.append(float(rec.t[steps[0]]))
                gates.append(int(rec.gates_passed[w, d]))
    return {"crashes": len(times), "time_s_p10_50_90": np.percentile(times, [10, 50, 90]).round(1).tolist()
            if times else [], "gates_passed": np.bincount(gates).tolist() if gates else []}


def beyond_range(policy: str, track: str, worlds: int = 64, steps: int = 500) -> list[float]:
    """Share of mean actions with |mu| > 1, per action, two copies of ``policy`` racing."""
    from cfrace.drone import DEFAULT_PROFILE, load_profile
    from cfrace.env.race_env import RaceEnv
    from cfrace.policy import resolve_policy
    from cfrace.rl.models import AgentModels
    from cfrace.rl.warmstart import warm_start
    from cfrace.track import load_track

    env = RaceEnv(load_track(track), load_profile(DEFAULT_PROFILE), num_envs=worlds, method="ours", obstacles=False,
                  seed=0)
    m = AgentModels(env.obs_dim, env.critic_dim, (128, 128), (256, 128), 0.2)
    warm_start(types.SimpleNamespace(agents=[m]), resolve_policy(policy, track, False), "race42")
    obs, _ = env.reset()
    out = []
    with torch.no_grad():
        for _ in range(steps):
            mu = m.actor(m.obs_norm(obs)).mean
            out.append(mu.reshape(-1, 4))
            obs = env.step(mu.clamp(-1.0, 1.0)).obs
    return (torch.cat(out).abs() > 1.0).float().mean(0).tolist()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--policy", default="ours")
    ap.add_argument("--field", default="ours,ours,ds,ds")
    ap.add_argument("--races", type=int, default=50)
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--track", default="lemniscate")
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(args.field, twin_crashes(args.policy, args.field.split(","), args.races, args.seed, args.track))
    print("share of mean actions beyond +-1 (per action):",
          [round(x, 3) for x in beyond_range(args.policy, args.track)])


if __name__ == "__main__":
    main()
