"""Wall time of the evaluation commands (docs/evaluation.md) with the shipped policies and in the
worst case, for docs/benchmarks.md ("Evaluation").

    .venv/bin/python benchmarks/eval_timing.py [--json F]

Runs each command once as a subprocess (the installed `cfrace` of this interpreter) and reports:
"library", the time inside evaluate / race / tournament (`wall_s` of the command's --json: loading
the policies, spawning, flying, metrics); "CLI", the whole command's wall time (Python start-up and
imports included); "CPU", the command's user + system CPU time. The worst case: paper-size actors
([512, 512, 256, 128], cfrace.rehearsal.hold_policy.make_sized_hold_policy) that hold their height
and never finish nor crash, so every world flies to the time limit. Say what else ran.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CFRACE = str(Path(sys.executable).with_name("cfrace"))
GOALS_S = {"eval": 30.0, "tournament": 120.0}


def timed(args: list[str], out: Path) -> dict:
    """One command: library s (from its --json), CLI wall s, CPU s."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([CFRACE, *args, "--json", str(out)], check=True, capture_output=True, env=dict(os.environ))
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    doc = json.loads(out.read_text())
    lib = doc.get("wall_s") if isinstance(doc, dict) else None
    if lib is None:                      # eval of several policies: one result each
        rows = doc if isinstance(doc, list) else doc.get("results", [])
        lib = sum(r.get("wall_s", 0.0) for r in rows)
    return {"library_s": round(lib, 2), "cli_s": round(wall, 2), "cpu_s": round(cpu, 2)}


def commands(tmp: Path) -> list[tuple[str, str, list[str]]]:
    from cfrace.rehearsal.hold_policy import make_sized_hold_policy

    solo = [str(make_sized_hold_policy(tmp / f"big_solo{i}.onnx", "solo36", "lemniscate", False, seed=i))
            for i in range(2)]
    duo = [str(make_sized_hold_policy(tmp / f"big_race{i}.onnx", "race42", "lemniscate", False, seed=2 + i))
           for i in range(4)]
    lem = ["--track", "lemniscate"]
    return [
        ("eval", "eval ds --runs 50 --laps 3", ["eval", "ds", *lem, "--runs", "50", "--laps", "3"]),
        ("eval", "same, worst case (paper-size hold actor)", ["eval", solo[0], *lem, "--runs", "50", "--laps", "3"]),
        ("race", "race --ego ours --opp ds --races 50", ["race", *lem, "--ego", "ours", "--opp", "ds", "--races", "50"]),
        ("race", "same, worst case", ["race", *lem, "--ego", duo[0], "--opp", duo[1], "--races", "50"]),
        ("tournament", "tournament ours ds ss dm --races 20 (6 pairs)",
         ["tournament", "ours", "ds", "ss", "dm", *lem, "--races", "20"]),
        ("tournament", "same, worst case (4 paper-size hold actors)", ["tournament", *duo, *lem, "--races", "20"]),
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    rows = []
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        for i, (kind, label, cmd) in enumerate(commands(tmp)):
            r = timed(cmd, tmp / f"out{i}.json")
            goal = GOALS_S.get(kind)
            r.update(command=label, goal_s=goal, met=None if goal is None else r["cli_s"] <= goal)
            rows.append(r)
            print(f"{label:48s} library {r['library_s']:6.1f} s  CLI {r['cli_s']:6.1f} s  CPU {r['cpu_s']:6.1f} s"
                  + ("" if goal is None else f"  goal {goal:.0f} s: {'met' if r['met'] else 'NOT met'}"), flush=True)
    load = (load0, os.getloadavg()[0])
    print(f"load average {load[0]:.2f} at the start, {load[1]:.2f} at the end, {os.cpu_count()} CPUs")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "load_avg": load}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
