"""CPU time of each flight-loop tick in which drones land, in `cfrace bench loop`.

    .venv/bin/python benchmarks/landing_ticks.py [--drones 8] [--track complex] [--duration-s 10] [--json FILE]
    PYTHONPATH=OLD_TREE .venv/bin/python benchmarks/landing_ticks.py ...     (another revision's code:
        git archive REV | tar -x -C OLD_TREE)

Runs `cfrace bench loop` in this process with each tick's CPU timed
(cfrace.rehearsal.loop_timing.landing_tick_cpu). At the bench's time-out every drone starts landing in
one tick. Prints the ticks with a landing drone, slowest first, and the racing ticks' p50 / p99 / max.
"""

from __future__ import annotations

import argparse
import json


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drones", type=int, default=8)
    ap.add_argument("--track", default="complex")
    ap.add_argument("--duration-s", type=float, default=10.0)
    ap.add_argument("--show", type=int, default=10, help="landing ticks to print")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    import cfrace
    from cfrace.rehearsal.loop_timing import landing_tick_cpu

    doc = {"cfrace": cfrace.__file__} | landing_tick_cpu(args.drones, args.track, args.duration_s)
    landing, racing = doc["landing_ticks_cpu_ms"], doc["racing_cpu_ms"]
    print(f"cfrace from {cfrace.__file__}")
    print(f"{len(landing)} ticks with a landing drone; slowest (CPU ms, tick, drones landing): "
          + ", ".join(f"{c:.2f} ({k}, {n})" for c, k, n in landing[:args.show]))
    print(f"racing ticks, CPU ms p50 {racing['p50']:.2f}, p99 {racing['p99']:.2f}, max {racing['max']:.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(doc, f, indent=1)


if __name__ == "__main__":
    main()
