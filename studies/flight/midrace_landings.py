"""One drone of a field told to land mid-race (a soft failsafe), at every step of a range of times:
does it land, and do the others race on?

    python studies/flight/midrace_landings.py [--track lemniscate] [--policies ours,ds,ours,ds] [--fault low_battery]
                                          [--drone d2] [--from 1] [--to 8] [--step 0.5] [--json F]

Lockstep dry-runs of the shipped policies (cf2x_paper, their training profile; 3 laps, ground start)
through the whole flight stack: first the race without the fault (the reference), then one race per
time T with ``FAULT@T:DRONE`` (each ended by the same time-out, 8 s after the last T). A race end is bad when the drone's landing did not end down, or when
a stop or landing event comes that the reference race does not have at the same time (other than
the fault's own). Prints one line per T and the count of bad ones; with ``PYTHONPATH`` at another
checkout it measures that code (docs/flight.md, "Landing mid-race").
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from cfrace.flight.config import FlightConfig
from cfrace.rehearsal.dryrun import dry_run


def race(track: str, policies: tuple, faults: str | None, timeout_s: float) -> dict:
    cfg = FlightConfig(track=track, ego=policies[0], opp=policies[1], policies=policies, profile="cf2x_paper",
                       laps=3, quiet=True, timeout_s=timeout_s)
    return dry_run(cfg, lockstep=True, faults=faults).to_json()


def acting(result: dict, since: float = 0.0) -> set:
    return {(round(e["t"], 2), e["kind"], e["drone"]) for e in result["safety_events"]
            if e["action"] != "none" and e["t"] >= since}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--track", default="lemniscate")
    ap.add_argument("--policies", default="ours,ds,ours,ds")
    ap.add_argument("--fault", default="low_battery")
    ap.add_argument("--drone", default="d2")
    ap.add_argument("--from", dest="t0", type=float, default=1.0)
    ap.add_argument("--to", dest="t1", type=float, default=8.0)
    ap.add_argument("--step", type=float, default=0.5)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    pols = tuple(args.policies.split(","))
    ref = acting(race(args.track, pols, None, args.t1 + 8.0))
    rows = []
    for t in np.round(np.arange(args.t0, args.t1 + 1e-9, args.step), 3):
        r = race(args.track, pols, f"{args.fault}@{t}:{args.drone}", args.t1 + 8.0)   # as the reference
        landing = next(d["landing"] for d in r["drones"] if d["name"] == args.drone)
        new = sorted(e for e in acting(r, t) - ref if e[1] != args.fault)
        down = landing is not None and bool(landing.get("down"))
        rows.append({"t": float(t), "landing_start": None if landing is None else landing.get("t_start"),
                     "down": down, "cut": None if landing is None else landing.get("cut"), "new_events": new,
                     "bad": bool(new) or not down})
        print(f"{t:.2f}: landing from {rows[-1]['landing_start']} down {down} cut {rows[-1]['cut']} "
              f"new events {new}", flush=True)
    bad = sum(r["bad"] for r in rows)
    print(f"{args.fault} on {args.drone}, {args.policies} on {args.track}: {bad} of {len(rows)} bad")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": vars(args), "rows": rows, "bad": bad}, f, indent=1)


if __name__ == "__main__":
    main()
