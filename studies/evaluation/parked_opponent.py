"""Where does a two-drone policy flying alone see its opponent? Its success alone under each choice.

    .venv/bin/python studies/evaluation/parked_opponent.py [--policies dm,ours] [--seeds 0,1,2,3] [--runs 50] [--json FILE]

`cfrace eval` of a multi-agent policy shows it an opponent that never moves
(cfrace.evaluate.rollout.parked_opponents): by default one that crashed at the start, on the floor in
the slot beside the drone's start. This flies every shipped policy of the given schemes on all four
settings (50 runs x 3 laps per seed) with the opponent there and, for comparison, on the floor in
each corner of the arena and at its centre. Prints a markdown table of success rates (mean over the
seeds, and the range) and one JSON document.
"""

from __future__ import annotations

import argparse
import json

import torch

SETTINGS = (("lemniscate", False), ("lemniscate", True), ("complex", False), ("complex", True))
SPOTS = ("start slot", "corner x_min y_min", "corner x_max y_max", "corner x_min y_max", "corner x_max y_min",
         "arena centre")


def spot_fn(name: str, default):
    """A replacement of parked_opponents putting the opponent at ``name`` (on the floor)."""
    if name == "start slot":
        return default

    def parked(track, profile, starts):
        a = track.arena
        x = {"x_min": a.x[0], "x_max": a.x[1]}
        y = {"y_min": a.y[0], "y_max": a.y[1]}
        if name == "arena centre":
            xy = ((a.x[0] + a.x[1]) / 2.0, (a.y[0] + a.y[1]) / 2.0)
        else:
            _, xs, ys = name.split()
            xy = (x[xs], y[ys])
        spot = torch.tensor([xy[0], xy[1], profile.collision_box[2] / 2.0], dtype=torch.float32)
        return spot.expand(starts.pos.shape[0], 3).clone()
    return parked


def main() -> None:
    from cfrace.evaluate import rollout
    from cfrace.evaluate.single import evaluate

    ap = argparse.ArgumentParser()
    ap.add_argument("--policies", default="dm,ours")
    ap.add_argument("--seeds", default="0,1,2,3")
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--json")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    default = rollout.parked_opponents
    rows = []
    try:
        for method in args.policies.split(","):
            for track, obstacles in SETTINGS:
                row = {"policy": method, "track": track, "obstacles": obstacles}
                for spot in SPOTS:
                    rollout.parked_opponents = spot_fn(spot, default)
                    rates = [evaluate([method], track, obstacles=obstacles, runs=args.runs, laps=3, seed=s)
                             .to_json()["success_rate"] for s in seeds]
                    row[spot] = rates
                rows.append(row)
                print(json.dumps(row), flush=True)
    finally:
        rollout.parked_opponents = default
    print("\n| policy | setting | " + " | ".join(SPOTS) + " |")
    print("|---|---|" + "---|" * len(SPOTS))
    for r in rows:
        cells = [f"{100 * sum(v) / len(v):.0f} ({100 * min(v):.0f}-{100 * max(v):.0f})" for v in (r[s] for s in SPOTS)]
        name = f"{r['track']}{' obstacles' if r['obstacles'] else ''}"
        print(f"| {r['policy']} | {name} | " + " | ".join(cells) + " |")
    doc = {"seeds": seeds, "runs": args.runs, "laps": 3, "rows": rows}
    if args.json:
        with open(args.json, "w") as f:
            json.dump(doc, f, indent=1)


if __name__ == "__main__":
    main()
