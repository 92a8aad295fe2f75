"""`cfrace bench sim|train|loop` of two code versions side by side, in one run, interleaved.

    python benchmarks/side_by_side.py OLD NEW [--rounds 2] [--benches sim,train,...] [--loop-s 10] [--json F]
    python benchmarks/side_by_side.py --pool F1.json,F2.json,...    (the rounds of earlier runs together)

OLD and NEW are checkout roots or git revisions of this repository (a revision's tree is taken with
`git archive` into a temporary directory; `.` is this checkout); each benchmark runs as A B B A A B
... (``rounds`` times each, the order turned every round, with the interpreter running this script
and PYTHONPATH=SRC), so that both see the same machine load and neither always runs second. Prints, per figure, the median of each
version and the ratio new/old as speed (higher is better: rates are new/old, latencies old/new).
Figures: bench sim (C kernel, 4096 worlds x 2 drones, one thread, 200 steps, best of 5), bench train (the cpu preset,
ours on complex, one thread), floor (the machine's floor of `bench loop --floor-s`: the clock with no work, --loop-s long),
bench loop (10 s, or --loop-s, the paper-size actors and the shipped policies, and 8 drones
on the complex track, all landing at its end: also the longest tick and the skipped ticks; lockstep_swarm8: the
tick's compute alone in a lockstep dry-run of 8 shipped policies (and its tick count: the same race); the jitter p99 of a 10-s
loop is its 10th-largest period error and moves with a handful of the VM's stalls: longer loops measure it better).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from loop_commits_ab import tree

BENCHES: dict[str, list[str]] = {
    "sim": ["bench", "sim", "--worlds", "4096", "--modes", "c", "--no-peer", "--threads", "1", "--steps", "200", "--repeats", "5"],
    "train": ["bench", "train", "--threads", "1", "--iterations", "2"],
    "loop_paper": ["bench", "loop", "--duration-s", "{loop_s}", "--floor-s", "0", "--policies", "paper"],
    "loop_shipped": ["bench", "loop", "--duration-s", "{loop_s}", "--floor-s", "0", "--policies", "shipped"],
    # the machine's floor: the loop's clock with no work (bare_loop: RealClock.wait_next, empty warm-up)
    "floor": ["bench", "loop", "--duration-s", "1", "--floor-s", "{loop_s}", "--policies", "shipped"],
    # 8 drones on the complex track: all of them start landing in the race's last tick
    "loop_swarm8": ["bench", "loop", "--duration-s", "{loop_s}", "--floor-s", "0", "--drones", "8", "--track", "complex"],
    # the tick's CPU work alone: 8 shipped policies from a hover start in lockstep (no sleep, no warm-up,
    # the same race tick for tick in both versions when they are bit-identical: benchmarks/dryrun_identical.py)
    "lockstep_swarm8": ["sim", "dry-run", "--track", "complex", "--policies", "ours,ds,ours,ds,ours,ds,ours,ds",
                        "--start", "hover", "--lockstep", "--quiet"],
}


def figures(name: str, doc: dict) -> dict[str, tuple[float, bool]]:
    """name -> (value, higher is better)."""
    if name == "sim":
        return {"sim drone-steps/s": (doc["results"][0]["drone_steps_per_s"], True)}
    if name == "train":
        return {"train env-steps/s": (doc["env_steps_per_s"], True)}
    if name == "floor":
        fl = doc["floor"]
        return {"floor jitter p50 ms": (fl["period_jitter_ms"]["p50"], False),
                "floor jitter p99 ms": (fl["period_jitter_ms"]["p99"], False),
                "floor tick late p99 ms": (fl["late_ms"]["p99"], False)}
    loop = doc["loop"]
    if name.startswith("lockstep"):
        return {f"{name} compute p50 ms": (loop["compute_ms"]["p50"], False),
                f"{name} compute p99 ms": (loop["compute_ms"]["p99"], False),
                f"{name} ticks": (loop["ticks"], False)}
    out = {f"{name} compute p50 ms": (loop["compute_ms"]["p50"], False),
           f"{name} compute p99 ms": (loop["compute_ms"]["p99"], False),
           f"{name} inference p99 ms": (loop["inference_p99_ms"], False),
           f"{name} jitter p99 ms": (loop["period_jitter_ms"]["p99"], False)}
    if name == "loop_swarm8":
        out[f"{name} compute max ms"] = (loop["compute_ms"]["max"], False)
        out[f"{name} skipped ticks"] = (loop["skipped"], False)
    return out


def run_one(src: Path, args: list[str], out: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(src), OMP_NUM_THREADS="1")
    code = f"import sys; sys.argv = {['cfrace', *args, '--json', str(out)]!r}; from cfrace.cli.main import main; main()"
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    # a dry-run whose race ended in a safety stop exits 3 with its result written (the fields' crashes)
    if proc.returncode != 0 and not (proc.returncode == 3 and out.exists()):
        raise SystemExit(f"{src}: cfrace {' '.join(args)} failed: {proc.stderr.strip()[-400:]}")
    return json.loads(out.read_text())


def source(arg: str, tmp: Path) -> Path:
    """A checkout root as given, or the tree of the git revision ``arg`` under ``tmp``."""
    if Path(arg).is_dir():
        return Path(arg).resolve()
    tmp.mkdir(parents=True)
    return tree(arg, tmp)


def pool(paths: list[str]) -> int:
    """The rounds of several --json runs together: per figure the medians, the speed and in how
    many rounds the new version was worse."""
    runs: dict[str, dict[str, list[float]]] = {}
    for p in paths:
        for row in json.loads(Path(p).read_text())["rows"]:
            r = runs.setdefault(row["figure"], {"old": [], "new": []})
            r["old"] += row["runs"]["old"]
            r["new"] += row["runs"]["new"]
    for fig, v in runs.items():
        old, new = statistics.median(v["old"]), statistics.median(v["new"])
        higher = fig.endswith("/s")                       # rates: higher is better; latencies: lower
        speed = new / old if higher else old / new if new else float("inf")
        worse = sum((b < a) if higher else (b > a) for a, b in zip(v["old"], v["new"]))
        print(f"{fig:32s} old {old:12.4g}  new {new:12.4g}  speed new/old {speed:.3f}x  "
              f"new worse in {worse} of {len(v['old'])} rounds")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old", nargs="?")
    ap.add_argument("new", nargs="?")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--benches", default="sim,train,loop_paper,loop_shipped", help=f"of {', '.join(BENCHES)}")
    ap.add_argument("--loop-s", type=float, default=10.0, help="seconds of each bench loop run")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--pool", default=None, help="comma-separated --json files of earlier runs")
    args = ap.parse_args()
    if args.pool:
        return pool(args.pool.split(","))
    if not (args.old and args.new):
        ap.error("OLD and NEW are required (or --pool)")
    values: dict[str, dict[str, list[float]]] = {}
    better: dict[str, bool] = {}
    loads = []
    with tempfile.TemporaryDirectory() as tmp:
        srcs = {label: source(arg, Path(tmp) / label) for label, arg in (("old", args.old), ("new", args.new))}
        for name in args.benches.split(","):
            for r in range(args.rounds):
                for label in (("old", "new") if r % 2 == 0 else ("new", "old")):   # A B B A ...
                    src = srcs[label]
                    loads.append(os.getloadavg()[0])
                    cmd = [a.format(loop_s=f"{args.loop_s:g}") for a in BENCHES[name]]
                    doc = run_one(src, cmd, Path(tmp) / f"{name}_{label}_{r}.json")
                    for fig, (v, hib) in figures(name, doc).items():
                        values.setdefault(fig, {"old": [], "new": []})[label].append(v)
                        better[fig] = hib
                    print(f"{name} round {r} {label}: " + ", ".join(f"{k} {v[0]:.4g}" for k, v in
                                                                  figures(name, doc).items()), flush=True)
    rows = []
    for fig, v in values.items():
        old, new = statistics.median(v["old"]), statistics.median(v["new"])
        speed = (new / old) if better[fig] else (old / new) if new else float("inf")
        rows.append({"figure": fig, "old": old, "new": new, "speed_new_over_old": speed, "runs": v})
        print(f"{fig:32s} old {old:12.4g}  new {new:12.4g}  speed new/old {speed:.3f}x")
    print(f"load average during the runs: {min(loads):.2f}-{max(loads):.2f} on {os.cpu_count()} CPUs")
    if args.json:
        args.json.write_text(json.dumps({"old": args.old, "new": args.new, "rounds": args.rounds, "loop_s": args.loop_s, "rows": rows,
                                         "load_avg": loads}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
