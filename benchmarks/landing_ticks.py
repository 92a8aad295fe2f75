"""CPU time of each flight-loop tick in which drones land, in `cfrace bench loop`.

    .venv/bin/python benchmarks/landing_ticks.py [--drones 8] [--track complex] [--duration-s 10] [--json FILE]
    PYTHONPATH=OLD_TREE .venv/bin/python benchmarks/landing_ticks.py ...     (another revision's code:
        git archive REV | tar -x -C OLD_TREE)

Runs `cfrace bench loop` in this process with cfrace.flight.loop.tick.TickCore.step timed (time.thread_time:
the loop thread's CPU, not the machine's load). At the bench's time-out every drone starts landing in
one tick. Prints the ticks with a landing drone, slowest first, and the racing ticks' p50 / p99 / max.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drones", type=int, default=8)
    ap.add_argument("--track", default="complex")
    ap.add_argument("--duration-s", type=float, default=10.0)
    ap.add_argument("--show", type=int, default=10, help="landing ticks to print")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    import cfrace
    import cfrace.flight.loop.tick as tick
    from cfrace.cli.main import main as cli

    ticks = []                       # (cpu s, k, drones landing)
    step = tick.TickCore.step

    def timed(self, t_in, *a, **kw):
        c0 = time.thread_time()
        out = step(self, t_in, *a, **kw)
        ticks.append((time.thread_time() - c0, t_in.k, sum(d.landing is not None for d in self.drones)))
        return out

    tick.TickCore.step = timed
    sys.argv = ["cfrace", "bench", "loop", "--drones", str(args.drones), "--track", args.track,
                "--duration-s", f"{args.duration_s:g}", "--floor-s", "0"]
    try:
        cli()
    except SystemExit as exc:
        if exc.code:
            raise
    landing = sorted((t for t in ticks if t[2]), reverse=True)
    racing = np.array([t[0] for t in ticks if not t[2]]) * 1e3
    print(f"cfrace from {cfrace.__file__}")
    print(f"{len(landing)} ticks with a landing drone; slowest (CPU ms, tick, drones landing): "
          + ", ".join(f"{c * 1e3:.2f} ({k}, {n})" for c, k, n in landing[:args.show]))
    print(f"racing ticks: {len(racing)}, CPU ms p50 {np.median(racing):.2f}, p99 {np.percentile(racing, 99):.2f}, "
          f"max {racing.max():.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"cfrace": cfrace.__file__, "drones": args.drones, "track": args.track,
                       "landing_ticks_cpu_ms": [[round(c * 1e3, 3), k, n] for c, k, n in landing],
                       "racing_cpu_ms": {"p50": float(np.median(racing)), "p99": float(np.percentile(racing, 99)),
                                         "max": float(racing.max())}}, f, indent=1)


if __name__ == "__main__":
    main()
