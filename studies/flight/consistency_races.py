"""The pose/command consistency check (cfrace/flight/mocap/consistency.py) on races of the shipped policies:
false stops and the largest residuals, lockstep dry-runs through the whole flight stack.

    python studies/flight/consistency_races.py [--races 50] [--pairs lemniscate:ours:ds,complex:ours:ds]
                                           [--noise-mm 1] [--json FILE]

Each race: `cfrace sim dry-run --lockstep` (seed = race index) with the track's shipped policies and
their training profile, mocap noise --noise-mm (the sim's poses are exact; a real system's are
not); the races are spread over the pairs in turn.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from cfrace.flight.config import FlightConfig
from cfrace.flight.mocap.consistency import RATE_LIMIT_DPS
from cfrace.rehearsal.dryrun import dry_run
from cfrace.flight.setup import training_profile
from cfrace.track import load_track


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--races", type=int, default=50)
    ap.add_argument("--pairs", default="lemniscate:ours:ds,complex:ours:ds")
    ap.add_argument("--noise-mm", type=float, default=1.0)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    pairs = [p.split(":") for p in args.pairs.split(",")]
    rows, stops, worst = [], 0, [0.0, 0.0]
    for k in range(args.races):
        track, ego, opp = pairs[k % len(pairs)]
        profile = training_profile(load_track(track), ego, False)
        cfg = FlightConfig(track=track, ego=ego, opp=opp, profile=profile, quiet=True, laps=3, timeout_s=60.0)
        r = dry_run(cfg, lockstep=True, seed=k, mocap_noise_m=args.noise_mm / 1e3).to_json()
        mism = [e for e in r["safety_events"] if e["kind"] == "pose_mismatch"]
        stops += len(mism)
        res = [d["pose_residual_max"] for d in r["drones"]]
        worst = [max(worst[0], *(x["rate_dps"] for x in res)), max(worst[1], *(x["dv_of_limit"] for x in res))]
        rows.append({"race": k, "track": track, "end": r["end"], "winner": r["winner"], "pose_mismatch": len(mism),
                     "residual_max": res, "stops": [d["stop_kind"] for d in r["drones"]]})
        print(f"race {k:2d} {track:10s} end {r['end']:12s} winner {r['winner']:4s} mismatch stops {len(mism)} "
              f"worst rate {max(x['rate_dps'] for x in res):6.1f} deg/s, dv {max(x['dv_of_limit'] for x in res):.2f} of its limit",
              flush=True)
    print(f"{args.races} races: {stops} pose_mismatch stops; largest residuals: {worst[0]:.1f} deg/s "
          f"(limit {RATE_LIMIT_DPS:g}), velocity change {worst[1]:.2f} of its limit")
    if args.json:
        Path(args.json).write_text(json.dumps({"races": args.races, "noise_mm": args.noise_mm, "false_stops": stops,
                                               "worst_rate_dps": worst[0], "worst_dv_of_limit": worst[1],
                                               "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
