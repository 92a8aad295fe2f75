"""Same behaviour check: `cfrace sim dry-run --lockstep` on the shipped policies, two code versions.

    python benchmarks/dryrun_identical.py run OUT_DIR [--pythonpath SRC]   # run the cases, JSON + MCAP
    python benchmarks/dryrun_identical.py compare DIR_A DIR_B [--json F --label L]   # bit-identical or not

`run` runs every case of CASES (two-drone races on the lemniscate, a fault case, 4- and 8-drone fields) with the interpreter running this script, the code of SRC (a
checkout's root, e.g. `git archive COMMIT | tar -x -C SRC`) or of the installed cfrace. `compare`
compares each case's JSON result and every message of its flight log (setpoints, actions,
observations, estimates, poses, events, race progress) for exact equality, leaving out only what
depends on the wall clock or the invocation: timing figures, start times, pid, command line, paths
(policy files are compared by name: both checkouts ship the same files).
Exit code 0 when every case is identical. With ``--json F`` the verdict per case is stored in F under
``--label`` (other labels in F are kept): benchmarks/results/dryrun_identical.json holds the
consolidation's steps (docs/architecture.md).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

CASES: dict[str, list[str]] = {
    "ours_ds": ["--ego", "ours", "--opp", "ds"],
    "ds_ours": ["--ego", "ds", "--opp", "ours"],
    "ss_dm": ["--ego", "ss", "--opp", "dm"],
    "dm_ss": ["--ego", "dm", "--opp", "ss"],
    "ours_ds_faults": ["--ego", "ours", "--opp", "ds", "--mocap-noise-m", "0.002", "--mocap-latency-ms", "20",
                       "--seed", "3", "--faults", "mocap_dropout_short@2:ego,pose_outlier@4:opp,nan_policy@9:opp"],
    # fields: twins in contact, landings among racing drones, one inference call per policy
    "field4": ["--policies", "ours,ours,ds,ds", "--seed", "1"],
    "field8_complex": ["--track", "complex", "--policies", "ours,ds,ours,ds,ours,ds,ours,ds", "--start", "hover"],
}
LOOP_KEEP = ("rate_hz", "ticks", "skipped")              #: loop figures that do not depend on the clock
META_DROP = ("start_time", "start_time_unix_s", "pid", "command", "cfrace_version")
TIMING_KEEP = ("k", "now", "late_s", "skipped")


def run(out: Path, pythonpath: str | None) -> None:
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    for name, args in CASES.items():
        track = [] if "--track" in args else ["--track", "lemniscate"]
        argv = ["cfrace", "sim", "dry-run", *track, "--lockstep", *args,
                "--json", str(out / f"{name}.json"), "--log", str(out / f"{name}.mcap")]
        code = f"import sys; sys.argv = {argv!r}; from cfrace.cli.main import main; main()"
        proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
        print(f"{name}: exit {proc.returncode}", flush=True)


def _result(path: Path) -> dict:
    r = json.loads(path.read_text())
    r.pop("log", None)
    r["loop"] = {k: r["loop"][k] for k in LOOP_KEEP if k in r.get("loop", {})}
    return r


def _messages(path: Path) -> dict[str, list]:
    from cfrace.flight.log.writer import read_log

    data = read_log(path)
    out = {}
    for topic in data.topics:
        msgs = []
        for t, m in data.messages(topic):
            m = dict(m)
            if topic == "/meta":
                for k in META_DROP:
                    m.pop(k, None)
            elif topic == "/timing":
                m = {k: m[k] for k in TIMING_KEEP if k in m}
            elif topic == "/summary":
                m.pop("log", None)
                m["loop"] = {k: m["loop"][k] for k in LOOP_KEEP if k in m.get("loop", {})}
            msgs.append((t, m))
        out[topic] = msgs
    return out


def _first_difference(a, b, where: str = "") -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            if k not in a or k not in b:
                return f"{where}.{k}: only in {'B' if k not in a else 'A'}"
            d = _first_difference(a[k], b[k], f"{where}.{k}")
            if d:
                return d
        return None
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            return f"{where}: {len(a)} items vs {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            d = _first_difference(x, y, f"{where}[{i}]")
            if d:
                return d
        return None
    if isinstance(a, str) and isinstance(b, str) and a.endswith(".onnx") and b.endswith(".onnx"):
        a, b = Path(a).name, Path(b).name   # the shipped policies of each checkout: the same files
    return None if a == b and type(a) is type(b) else f"{where}: {a!r} vs {b!r}"


def compare(a: Path, b: Path, json_out: Path | None = None, label: str | None = None) -> int:
    failures = 0
    verdicts = {}
    for name in CASES:
        ja, jb = a / f"{name}.json", b / f"{name}.json"
        if not ja.exists() or not jb.exists():
            print(f"{name}: missing result ({ja if not ja.exists() else jb})")
            verdicts[name] = "missing result"
            failures += 1
            continue
        diff = _first_difference(_result(ja), _result(jb), "result")
        ma, mb = _messages(a / f"{name}.mcap"), _messages(b / f"{name}.mcap")
        diff = diff or _first_difference(ma, mb, "log")
        n = sum(len(v) for v in ma.values())
        summary = json.loads(ja.read_text())
        print(f"{name}: {'identical' if diff is None else 'DIFFERENT ' + diff} ({n} log messages, "
              f"end {summary['end']}, winner {summary['winner']}, {summary['loop']['ticks']} ticks)")
        verdicts[name] = {"identical": diff is None, "first_difference": diff, "log_messages": n,
                          "end": summary["end"], "winner": summary["winner"], "ticks": summary["loop"]["ticks"]}
        failures += diff is not None
    if json_out is not None:
        doc = json.loads(json_out.read_text()) if json_out.exists() else {}
        doc[label or f"{a} vs {b}"] = verdicts
        json_out.write_text(json.dumps(doc, indent=1) + "\n")
    return 1 if failures else 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("out", type=Path)
    r.add_argument("--pythonpath", default=None)
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    c.add_argument("--json", type=Path, default=None, help="store the verdicts in this JSON file")
    c.add_argument("--label", default=None, help="their key in it (default 'A vs B')")
    args = ap.parse_args()
    if args.cmd == "run":
        run(args.out, args.pythonpath)
        return 0
    return compare(args.a, args.b, args.json, args.label)


if __name__ == "__main__":
    sys.exit(main())
