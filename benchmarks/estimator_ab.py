"""The pose estimator's update (`PoseEstimator.update`, on every 100 Hz tick) of two commits, timed
in one process, interleaved.

    python benchmarks/estimator_ab.py OLD_REV [--rounds 5] [--ticks 3000] [--bodies 2] [--json FILE]

OLD_REV's `cfrace/flight/estimator.py` (and the modules it imports) is taken with `git archive`; the
new side is this checkout. Both estimators get the same frames: ``bodies`` bodies on circles at
100 Hz with one outlier every 50 frames, with the latency compensation on (``lead_s`` 10 ms, as
`fly` flies). Each round times ``ticks`` updates of each side back to back, then the same every
10 ms with a sleep in between (how the loop calls it, caches cold), in turned order; prints the
medians over rounds of the per-update time (us) and the ratio new / old. The machine is shared:
say what else ran (the load average is printed).
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from loop_commits_ab import REPO, tree


def load(src: Path):
    """cfrace.flight.estimator and cfrace.flight.mocap_base of the checkout at ``src`` (fresh imports)."""
    for name in [m for m in sys.modules if m == "cfrace" or m.startswith("cfrace.")]:
        del sys.modules[name]
    sys.path.insert(0, str(src))
    try:
        return importlib.import_module("cfrace.flight.estimator"), importlib.import_module("cfrace.flight.mocap_base")
    finally:
        sys.path.remove(str(src))


def frames(mocap_base, n: int, bodies: int) -> list:
    out = []
    for k in range(n):
        t = k * 0.01
        poses = {}
        for b in range(bodies):
            a = 0.8 * t + b
            pos = np.array([math.cos(a), math.sin(a), 1.0 + 0.1 * b]) + (2.0 if k % 50 == 25 else 0.0)
            quat = np.array([math.cos(a / 2), 0.0, 0.0, math.sin(a / 2)])
            poses[f"cf{b + 1}"] = mocap_base.Pose(pos, quat)
        out.append(mocap_base.MocapFrame(t, poses, k + 1))
    return out


def time_updates(est_mod, fs: list, bodies: int, sleep_s: float) -> float:
    """Median us per update."""
    est = est_mod.PoseEstimator([f"cf{b + 1}" for b in range(bodies)], lead_s=0.01)
    dts = []
    for f in fs:
        if sleep_s:
            time.sleep(sleep_s)
        t0 = time.perf_counter_ns()
        est.update(f, f.t)
        dts.append(time.perf_counter_ns() - t0)
    return statistics.median(dts) / 1e3


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old_rev")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--ticks", type=int, default=3000)
    ap.add_argument("--bodies", type=int, default=2)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="cfrace-est-") as tmp:
        mods = {"old": load(tree(args.old_rev, Path(tmp))), "new": load(REPO)}
    inputs = {side: frames(m[1], args.ticks, args.bodies) for side, m in mods.items()}
    cold_n = min(args.ticks, 300)
    res: dict[str, dict[str, list[float]]] = {s: {"back_to_back_us": [], "every_10ms_us": []} for s in mods}
    loads = []
    for r in range(args.rounds):
        for side in (("old", "new") if r % 2 == 0 else ("new", "old")):
            loads.append(os.getloadavg()[0])
            res[side]["back_to_back_us"].append(time_updates(mods[side][0], inputs[side], args.bodies, 0.0))
            res[side]["every_10ms_us"].append(time_updates(mods[side][0], inputs[side][:cold_n], args.bodies, 0.01))
    rows = {}
    for fig in ("back_to_back_us", "every_10ms_us"):
        old, new = statistics.median(res["old"][fig]), statistics.median(res["new"][fig])
        rows[fig] = {"old": old, "new": new, "new_over_old": round(new / old, 3)}
        print(f"{fig:16s} old {old:7.2f} us  new {new:7.2f} us  new/old {new / old:.3f}")
    print(f"load average during the runs: {min(loads):.2f}-{max(loads):.2f} on {os.cpu_count()} CPUs")
    if args.json:
        Path(args.json).write_text(json.dumps({"old_rev": args.old_rev, "rounds": args.rounds, "ticks": args.ticks,
                                               "bodies": args.bodies, "rows": rows, "runs": res,
                                               "load_avg": loads}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
