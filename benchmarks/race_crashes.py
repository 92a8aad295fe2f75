"""Where a policy crashes in head-to-head races: the crash reason, when, and where its opponent was.

    .venv/bin/python benchmarks/race_crashes.py EGO [--opp ds] [--track complex] [--obstacles]
                                                [--races 50] [--seed 0] [--near 1.5] [--list]

The races of `cfrace race --track T --ego EGO --opp OPP --races N --seed S` (the same starts: gate
starts, the sides swapped every other race, 3 laps: cfrace.evaluate.race.race). For every race EGO
crashes in: the crash
reason (cfrace.sim.simulator.REASONS), the time, the distance to the opponent and EGO's lead over
it along the race line at that step. Prints the counts by reason, how many crashes had the live
opponent within ``--near`` m, and (``--list``) one line per crash.
"""

from __future__ import annotations

import argparse
from collections import Counter

import numpy as np
import torch

from cfrace.evaluate.race import race_crashes


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("ego")
    ap.add_argument("--opp", default="ds")
    ap.add_argument("--track", default="complex")
    ap.add_argument("--obstacles", action="store_true")
    ap.add_argument("--races", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--near", type=float, default=1.5)
    ap.add_argument("--list", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = race_crashes(args.ego, args.opp, args.track, args.obstacles, args.races, args.seed)
    near = [r for r in rows if r["opp_racing"] and r["opp_dist_m"] < args.near]
    print(f"{args.ego} vs {args.opp}: crashes in {len(rows)} of {args.races} races; by reason "
          f"{dict(Counter(r['reason'] for r in rows))}; with the live opponent within {args.near} m: {len(near)}")
    if rows:
        print("crash time s p10/50/90:", np.percentile([r["t_s"] for r in rows], [10, 50, 90]).round(2).tolist())
    for r in rows if args.list else ():
        print("race {race:3d}  t {t_s:5.2f} s  {reason:12s}  opponent {opp_dist_m:5.2f} m away, lead {lead_m:6.2f} m"
              "  at {track_pos_m:6.1f} m of the race line{}".format("" if r["opp_racing"] else " (opponent down)", **r))


if __name__ == "__main__":
    main()
