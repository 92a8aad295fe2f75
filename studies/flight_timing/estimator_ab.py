"""The pose estimator's update (`PoseEstimator.update`, on every 100 Hz tick) of two commits, timed
in one process, interleaved.

    python studies/flight_timing/estimator_ab.py OLD_REV [--rounds 40] [--block 200] [--cold-block 20] [--bodies 2] [--json FILE]

OLD_REV's estimator (`cfrace/flight/mocap/estimation.py`, `cfrace/flight/estimator.py` before
the split by concern, and the modules it imports) is taken with `git archive`; the
new side is this checkout. Both estimators get the same frames: ``bodies`` bodies on circles at
100 Hz with one outlier every 50 frames, with the latency compensation on (``lead_s`` 10 ms, as
`fly` flies). Each round times a block of updates of each side back to back, then a smaller one
every 10 ms with a sleep in between (how the loop calls it, caches cold), the sides in turned order;
prints the medians over rounds of each block's median time per update (us) and the median of the
rounds' ratios new / old (paired: a slow spell of the shared machine hits both sides of a round). The machine is shared:
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

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from loop_commits_ab import REPO, tree  # noqa: E402  (the maintained tool's git archive of a revision)

#: the estimator's module and the mocap types' module, by layout: since the split of flight/ by concern, before it
LAYOUTS = (("cfrace.flight.mocap.estimation", "cfrace.flight.mocap.base"),
           ("cfrace.flight.estimator", "cfrace.flight.mocap_base"))


def load(src: Path):
    """The estimator's module and the mocap types' module of the checkout at ``src`` (fresh imports)."""
    for name in [m for m in sys.modules if m == "cfrace" or m.startswith("cfrace.")]:
        del sys.modules[name]
    estimator, mocap_base = next(mods for mods in LAYOUTS
                                 if (src / (mods[0].replace(".", "/") + ".py")).is_file())
    sys.path.insert(0, str(src))
    try:
        return importlib.import_module(estimator), importlib.import_module(mocap_base)
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


def time_block(est, fs: list, sleep_s: float) -> float:
    """Median ns per update over the frames ``fs`` (``sleep_s`` before each)."""
    dts = []
    for f in fs:
        if sleep_s:
            time.sleep(sleep_s)
        t0 = time.perf_counter_ns()
        est.update(f, f.t)
        dts.append(time.perf_counter_ns() - t0)
    return statistics.median(dts)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old_rev")
    ap.add_argument("--rounds", type=int, default=40)
    ap.add_argument("--block", type=int, default=200, help="updates per side and round, back to back")
    ap.add_argument("--cold-block", type=int, default=20, help="updates per side and round, every 10 ms")
    ap.add_argument("--bodies", type=int, default=2)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="cfrace-est-") as tmp:
        mods = {"old": load(tree(args.old_rev, Path(tmp))), "new": load(REPO)}
    names = [f"cf{b + 1}" for b in range(args.bodies)]
    ests = {side: m[0].PoseEstimator(names, lead_s=0.01) for side, m in mods.items()}
    inputs = {side: frames(m[1], args.rounds * (args.block + args.cold_block), args.bodies) for side, m in mods.items()}
    res: dict[str, dict[str, list[float]]] = {s: {"back_to_back_us": [], "every_10ms_us": []} for s in mods}
    loads = []
    k = 0
    for r in range(args.rounds):      # each round: a block of each side, in turned order (paired ratios)
        for fig, n, sleep_s in (("back_to_back_us", args.block, 0.0), ("every_10ms_us", args.cold_block, 0.01)):
            for side in (("old", "new") if r % 2 == 0 else ("new", "old")):
                res[side][fig].append(time_block(ests[side], inputs[side][k:k + n], sleep_s) / 1e3)
            k += n
        loads.append(os.getloadavg()[0])
    rows = {}
    for fig in ("back_to_back_us", "every_10ms_us"):
        old, new = statistics.median(res["old"][fig]), statistics.median(res["new"][fig])
        paired = statistics.median(n / o for n, o in zip(res["new"][fig], res["old"][fig]))
        rows[fig] = {"old": old, "new": new, "new_over_old_paired": round(paired, 3)}
        print(f"{fig:16s} old {old:7.2f} us  new {new:7.2f} us  new/old (median of the rounds' ratios) {paired:.3f}")
    print(f"load average during the runs: {min(loads):.2f}-{max(loads):.2f} on {os.cpu_count()} CPUs")
    if args.json:
        Path(args.json).write_text(json.dumps({"old_rev": args.old_rev, "rounds": args.rounds, "block": args.block,
                                               "cold_block": args.cold_block,
                                               "bodies": args.bodies, "rows": rows, "runs": res,
                                               "load_avg": loads}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
