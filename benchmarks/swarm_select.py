"""Choose a checkpoint of an N-drone training run on validation races in N-drone fields.

    .venv/bin/python benchmarks/swarm_select.py RUN [--against '*,*,ds,ds'] [--races 50] [--seed 100]
                                                [--track lemniscate] [--agent best] [--max-points 8] [--min-iteration 41]
                                                [--h2h ds [--h2h-seed 0] [--h2h-min 0.66]]

Every kept checkpoint (``cfrace train --keep-checkpoints``) is exported and raced in the field
``--against`` (``*`` = the checkpoint; cfrace.reproduction.select); prints one row per checkpoint and
the chosen one, writes RUN/checkpoints/scores.csv. With ``--h2h OPP`` every checkpoint also races
OPP head to head (``--races`` races, seed ``--h2h-seed``: the head-to-head validation seed), and the
choice is the highest field win rate among the checkpoints that win at least ``--h2h-min`` of those
races (ties: the earliest). Report the chosen policy on other seeds (`cfrace race --entrants ... --seed S`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch


def main() -> None:
    from cfrace.reproduction.select import score_checkpoint, score_run

    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--against", default="*,*,ds,ds")
    ap.add_argument("--races", type=int, default=50)
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--track", default="lemniscate")
    ap.add_argument("--agent", default="best")
    ap.add_argument("--max-points", type=int, default=None)
    ap.add_argument("--min-iteration", type=int, default=0, help="skip the critic warm-up's checkpoints")
    ap.add_argument("--h2h", default=None, help="also race this policy head to head (e.g. ds)")
    ap.add_argument("--h2h-seed", type=int, default=0)
    ap.add_argument("--h2h-min", type=float, default=0.66, help="least head-to-head win rate of a chosen checkpoint")
    args = ap.parse_args()
    torch.set_num_threads(1)

    def on_row(r: dict) -> None:
        if args.h2h:
            h = score_checkpoint(Path(r["checkpoint"]), args.track, False, args.h2h, args.races, 3, args.h2h_seed,
                                 args.agent)
            r["h2h_win"], r["h2h_loss"] = h["win_rate"], h["loss_rate"]
        h2h = f" {r['h2h_win']:.0%} / {r['h2h_loss']:.0%} |" if args.h2h else ""
        print(f"| {r['iteration']} | {r['env_steps']:,} | {r['wall_min']} | {r['win_rate']:.0%} | "
              f"{r['loss_rate']:.0%} |{h2h}", flush=True)

    h2h_head = f" against {args.h2h} (seed {args.h2h_seed}): won / lost |" if args.h2h else ""
    print(f"| iteration | env steps | min | first place (a * drone) | other winner |{h2h_head}")
    print("|---|---|---|---|---|" + ("---|" if args.h2h else ""))
    scored = score_run(args.run, args.track, False, args.against, args.races, 3, args.seed, args.agent,
                       on_row=on_row, max_points=args.max_points, min_iteration=args.min_iteration)
    c = scored.chosen
    if args.h2h:
        ok = [r for r in scored.rows if r["h2h_win"] >= args.h2h_min]
        if not ok:
            print(f"no checkpoint wins {args.h2h_min:.0%} against {args.h2h} on seed {args.h2h_seed}")
            return
        c = min(ok, key=lambda r: (-r["win_rate"], r["iteration"]))
    print(f"chosen: iteration {c['iteration']} ({c['onnx']}), first place {c['win_rate']:.0%} on seed {args.seed}"
          + (f", against {args.h2h} {c['h2h_win']:.0%} on seed {args.h2h_seed}" if args.h2h else ""))


if __name__ == "__main__":
    main()
