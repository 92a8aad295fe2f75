"""Choose a checkpoint of an N-drone training run on validation races in N-drone fields.

    .venv/bin/python benchmarks/swarm_select.py RUN [--against '*,*,ds,ds'] [--races 50] [--seed 100]
                                                [--track lemniscate] [--agent best] [--max-points 8] [--min-iteration 41]

Every kept checkpoint (``cfrace train --keep-checkpoints``) is exported and raced in the field
``--against`` (``*`` = the checkpoint; cfrace.evaluate.select); prints one row per checkpoint and
the chosen one, writes RUN/checkpoints/scores.csv. Report the chosen policy on other seeds
(`cfrace race --entrants ... --seed S`).
"""

from __future__ import annotations

import argparse

import torch


def main() -> None:
    from cfrace.evaluate.select import score_run

    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--against", default="*,*,ds,ds")
    ap.add_argument("--races", type=int, default=50)
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--track", default="lemniscate")
    ap.add_argument("--agent", default="best")
    ap.add_argument("--max-points", type=int, default=None)
    ap.add_argument("--min-iteration", type=int, default=0, help="skip the critic warm-up's checkpoints")
    args = ap.parse_args()
    torch.set_num_threads(1)
    print("| iteration | env steps | min | first place (a * drone) | other winner |")
    print("|---|---|---|---|---|")
    scored = score_run(args.run, args.track, False, args.against, args.races, 3, args.seed, args.agent,
                       on_row=lambda r: print(f"| {r['iteration']} | {r['env_steps']:,} | {r['wall_min']} | "
                                              f"{r['win_rate']:.0%} | {r['loss_rate']:.0%} |", flush=True),
                       max_points=args.max_points, min_iteration=args.min_iteration)
    c = scored.chosen
    print(f"chosen: iteration {c['iteration']} ({c['onnx']}), first place {c['win_rate']:.0%} on seed {args.seed}")


if __name__ == "__main__":
    main()
