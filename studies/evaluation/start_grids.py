"""How much of an N-drone race is decided by the start grid? Races of one lineup from other grids.

    .venv/bin/python studies/evaluation/start_grids.py [--lineup ours,ours,ds,ds] [--seeds 100,101,102] [--races 50]
                                               [--track lemniscate] [--json FILE]

The track's grid (cfrace.track.start_grid: rows of two side by side, one offset apart, centred on
the spawn distance) against grids no command offers, each with its front drone at the spawn
distance and the others behind it: "staggered" (every drone in its own row, rows one offset apart,
sides alternating, as a motor-racing grid), "staggered, half rows" (rows half an offset apart) and
"single file" (one behind the other, one offset apart). Each is put in place of start_grid for the
race's start draws (RaceEnv.spawn, which draws again a start with a slot outside the arena), gate
starts, `cfrace.evaluate.field.race_field`; one thread. Prints a markdown table of first places by
policy and races without a winner, and one JSON document.
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def staggered(row_gap: float):
    def grid(spawn, gate, drones: int) -> np.ndarray:
        off = spawn.opponent_offset
        out = np.array([[((k % 2) - 0.5) * off, k * row_gap * off] for k in range(drones)], dtype=np.float64)
        return out        # the front drone at the spawn distance, the others behind it
    return grid


def single_file(spawn, gate, drones: int) -> np.ndarray:
    return np.array([[0.0, k * spawn.opponent_offset] for k in range(drones)], dtype=np.float64)


def main() -> None:
    import cfrace.env.race_env as race_env
    from cfrace.evaluate.field import race_field

    ap = argparse.ArgumentParser()
    ap.add_argument("--lineup", default="ours,ours,ds,ds")
    ap.add_argument("--seeds", default="100,101,102")
    ap.add_argument("--races", type=int, default=50)
    ap.add_argument("--track", default="lemniscate")
    ap.add_argument("--json")
    args = ap.parse_args()
    grids = {"rows of two (the track's)": race_env.start_grid, "staggered": staggered(1.0),
             "staggered, half rows": staggered(0.5), "single file": single_file}
    default, rows = race_env.start_grid, []
    try:
        for name, grid in grids.items():
            race_env.start_grid = grid
            per_seed = []
            for seed in (int(s) for s in args.seeds.split(",")):
                d = race_field(args.track, args.lineup.split(","), races=args.races, seed=seed, threads=1).to_json()
                per_seed.append({"seed": seed, "first": d["policy_win_rate"], "no_winner": d["no_winner_rate"]})
            rows.append({"grid": name, "seeds": per_seed})
            print(json.dumps(rows[-1]), flush=True)
    finally:
        race_env.start_grid = default
    policies = list(rows[0]["seeds"][0]["first"])
    print(f"\n| grid | " + " | ".join(f"{p} first" for p in policies) + " | no winner |")
    print("|---|" + "---|" * (len(policies) + 1))
    for r in rows:
        cell = lambda vals: f"{100 * np.mean(vals):.1f} % ({' / '.join(f'{100 * v:.0f}' for v in vals)})"
        cells = [cell([s["first"][p] for s in r["seeds"]]) for p in policies] + [cell([s["no_winner"] for s in r["seeds"]])]
        print(f"| {r['grid']} | " + " | ".join(cells) + " |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"track": args.track, "lineup": args.lineup, "races": args.races, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
