"""Where the flight loop's tick goes: `cfrace bench loop` with a timer around each part.

    python benchmarks/loop_sections.py [--seconds 10] [--policies paper|shipped]

Runs the unchanged loop against `cfrace sim serve` in real time (cfrace.rehearsal.loop_timing) and
wraps the mocap read, pose estimator, race progress, safety check and each cflib send with
time.perf_counter; prints p50/p90/p99 per part in microseconds, then the loop's own figures.
The wrappers add about 1 us per call; calls made by the warm-up before each tick
(FlightLoop.prewarm) are not counted. Used for the table in docs/benchmarks.md ("Flight loop,
quiet machine").
"""

from __future__ import annotations

import argparse
import collections
import time

import numpy as np

import cfrace.flight.loop.flight_loop as loop_mod
from cfrace.flight.safety import check as sf
from cfrace.rehearsal.loop_timing import bench_loop

TIMES: dict[str, list[float]] = collections.defaultdict(list)


WARMING = [False]   # inside FlightLoop.prewarm: those calls are not the tick's, not recorded


def _wrap(obj, name: str, key: str) -> None:
    f = getattr(obj, name)

    def timed(*a, **k):
        if WARMING[0]:
            return f(*a, **k)
        t = time.perf_counter()
        r = f(*a, **k)
        TIMES[key].append(time.perf_counter() - t)
        return r

    setattr(obj, name, timed)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--policies", default="paper", choices=["paper", "shipped"])
    ap.add_argument("--prewarm-ms", type=float, default=None, help="as `cfrace bench loop` (default: its default)")
    args = ap.parse_args()
    _wrap(sf, "check", "safety check")
    init = loop_mod.FlightLoop.__init__

    def patched(self, **kw):
        init(self, **kw)
        _wrap(self.mocap, "read", "mocap read")
        _wrap(self.estimator, "update", "estimator")
        _wrap(self.progress, "update", "race progress")
        for d in self.drones:
            _wrap(d.link, "send", "cflib send (each)")

    loop_mod.FlightLoop.__init__ = patched
    prewarm = loop_mod.FlightLoop.prewarm

    def warm(self):
        WARMING[0] = True
        try:
            prewarm(self)
        finally:
            WARMING[0] = False

    loop_mod.FlightLoop.prewarm = warm
    kw = {} if args.prewarm_ms is None else {"prewarm_s": args.prewarm_ms / 1e3}
    res = bench_loop(args.seconds, policies=args.policies, **kw)
    print(f"{'part':22s} {'calls':>6s} {'p50 us':>8s} {'p90 us':>8s} {'p99 us':>8s}")
    for key, values in TIMES.items():
        v = np.asarray(values) * 1e6
        p50, p90, p99 = np.percentile(v, [50, 90, 99])
        print(f"{key:22s} {len(v):6d} {p50:8.1f} {p90:8.1f} {p99:8.1f}")
    loop = res["loop"]
    for name in ("compute_ms", "compute_cpu_ms", "period_jitter_ms"):
        print(f"{name:22s} p50 {loop[name]['p50']:.3f}  p99 {loop[name]['p99']:.3f} ms")
    for who, d in loop["inference_ms"].items():
        print(f"inference {who:12s} p50 {d['p50']:.3f}  p99 {d['p99']:.3f} ms")
    for who, d in loop["observation_ms"].items():
        print(f"observation {who:10s} p50 {d['p50']:.3f}  p99 {d['p99']:.3f} ms")


if __name__ == "__main__":
    main()
