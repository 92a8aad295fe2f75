"""Mocap latency against its compensation: each shipped lemniscate policy alone through the lockstep
flight stack (docs/flight.md, "Mocap latency").

    .venv/bin/python studies/flight/latency_matrix.py [--latencies 0,10,20,30,40] [--seeds 1,2,3]
                                                  [--profile trained] [--json F]

Per (policy, latency L ms, compensation C ms, seed): the run of
`cfrace sim dry-run --track lemniscate --ego P --opp ds --lockstep --laps 2 --mocap-latency-ms L
--latency-comp-ms C --mocap-noise-m 0.001 --faults nan_policy@0.02:opp --seed S --profile PROFILE`
(the opponent is stopped at once and lies at its start), through `cfrace.rehearsal.dryrun.dry_run`,
the function behind the command. C is 0 and L (and 10 for L = 0). Prints laps flown of 2 and how
each run ended (the ego's stop kind when it did not finish).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def one_run(policy: str, latency_ms: float, comp_ms: float, seed: int, profile: str) -> dict:
    from cfrace.cli.common import choose_profile
    from cfrace.flight.config import FlightConfig
    from cfrace.rehearsal.dryrun import dry_run
    from cfrace.track import load_track

    track = load_track("lemniscate")
    name, _ = choose_profile(profile, track, policy, False, {}, None)
    cfg = FlightConfig(track="lemniscate", ego=policy, opp="ds", laps=2, profile=name, quiet=True,
                       latency_comp_s=comp_ms / 1e3)
    res = dry_run(cfg, lockstep=True, faults="nan_policy@0.02:opp", seed=seed, mocap_noise_m=0.001,
                  mocap_latency_s=latency_ms / 1e3).to_json()
    ego = res["drones"][0]
    return {"policy": policy, "latency_ms": latency_ms, "comp_ms": comp_ms, "seed": seed, "laps": ego["laps"],
            "end": "2 laps" if ego["laps"] >= 2 else (ego.get("stop_kind") or res["end"])}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--latencies", default="0,10,20,30,40")
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--profile", default="trained")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    rows = []
    for policy in ("ours", "ds"):
        for lat in (float(v) for v in args.latencies.split(",")):
            for comp in sorted({0.0, lat, 10.0} if lat == 0 else {0.0, lat}):
                runs = [one_run(policy, lat, comp, int(s), args.profile) for s in args.seeds.split(",")]
                rows += runs
                print(f"{policy:5s} latency {lat:4.0f} ms  comp {comp:4.0f} ms  laps {[r['laps'] for r in runs]}  "
                      f"{', '.join(r['end'] for r in runs)}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"profile": args.profile, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
