"""The flight loop's timing with and without the warm-up window, side by side, interleaved.

    python studies/flight_timing/loop_warmup_ab.py [--leads 0,1,3,5] [--rounds 3] [--seconds 8]
                                        [--policies paper|shipped] [--loop-cpu off|auto|N]
                                        [--rt-priority 0|auto|N] [--json FILE]

studies/flight_timing/loop_ab.py with one setting per warm-up window (window 0 = off is the reference). Used
for docs/benchmarks.md ("Warm-up window"; those runs predate pinning and SCHED_FIFO by default, so
the defaults here are the loop unpinned at normal priority, as then).
"""

from __future__ import annotations

import argparse

from loop_ab import run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--leads", default="0,1,3,5", help="warm-up windows in ms, comma-separated (0 = off)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--policies", default="paper", choices=["paper", "shipped"])
    ap.add_argument("--loop-cpu", default="off")
    ap.add_argument("--rt-priority", default="0")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    configs = {f"{float(ms):g}ms": {"prewarm_s": float(ms) / 1e3, "loop_cpu": args.loop_cpu,
                                  "rt_priority": args.rt_priority}
               for ms in args.leads.split(",")}
    run(configs, args.rounds, args.seconds, args.policies, args.json)


if __name__ == "__main__":
    main()
