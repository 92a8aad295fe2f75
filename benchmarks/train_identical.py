"""Same learning check: fixed-seed 2-iteration trainings, two code versions, bit-identical or not.

    python benchmarks/train_identical.py run OUT_DIR [--pythonpath SRC]   # train every case, digests to JSON
    python benchmarks/train_identical.py compare DIR_A DIR_B              # identical or not

`run` trains each case of CASES (`cfrace train`, 64 worlds, 2 iterations, one thread) with the
interpreter running this script and the code of SRC (a checkout's root, e.g. `git worktree add
/tmp/old COMMIT`) or of the installed cfrace, and writes per case a SHA-256 of every tensor of the
final checkpoint (actors, critics, normalisers, Adam moments, torch RNG states) and the metrics rows
without their timing columns. `compare` reports each case identical or not (exit code 0 when all are).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ENVS = 64
COMMON = ["--track", "lemniscate", "--envs", str(ENVS), "--threads", "1", "--seed", "7"]
CASES: dict[str, list[str]] = {
    "ds_fp32": ["--method", "ds", "--precision", "fp32"],
    "ds_bf16": ["--method", "ds", "--precision", "bf16"],
    "ours_fixed_opponent": ["--method", "ours", "--precision", "fp32", "--random-phase", "--episode-s", "1",
                            "--fixed-opponent", "policies/ds_lemniscate.onnx", "--fixed-opponent-frac", "0.5"],
    "ours_warm_start": ["--method", "ours", "--precision", "fp32", "--init-from", "policies/ours_lemniscate.onnx",
                        "--critic-warmup", "1"],
    "dm_shared_3": ["--method", "dm", "--precision", "fp32", "--drones", "3", "--set", "shared=true"],
}
TIMING = ("fps", "iter_s", "sim_s", "infer_s", "update_s", "wall_s")

DIGEST = r"""
import hashlib, json, sys, torch
from cfrace.rl.checkpoint import load_checkpoint
ck = load_checkpoint(sys.argv[1])
def walk(x, key=""):
    if isinstance(x, torch.Tensor):
        yield key, hashlib.sha256(x.detach().cpu().contiguous().numpy().tobytes()).hexdigest()[:16]
    elif isinstance(x, dict):
        for k in sorted(x, key=str):
            yield from walk(x[k], f"{key}/{k}")
    elif isinstance(x, (list, tuple)):
        for i, v in enumerate(x):
            yield from walk(v, f"{key}/{i}")
    elif isinstance(x, (int, float, str, bool)) or x is None:
        yield key, repr(x)
r = ck["runner"]
r["rng"] = {k: v for k, v in r["rng"].items() if k != "python"}  # never seeded by the trainer
out = dict(walk({k: r[k] for k in ("agents", "optimizers", "lrs", "total_reward", "iteration", "env_steps",
                                    "obs", "critic", "ep_return", "rng")}))
print(json.dumps(out))
"""


def run(out: Path, pythonpath: str | None) -> None:
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    cwd = pythonpath or str(Path(__file__).resolve().parents[1])
    for name, args in CASES.items():
        run_dir = out / name
        rollout = 24 if "ds" in args else 16
        argv = ["cfrace", "train", *COMMON, *args, "--steps", str(2 * rollout * ENVS), "--out", str(run_dir)]
        code = f"import sys; sys.argv = {argv!r}; from cfrace.cli.main import main; main()"
        proc = subprocess.run([sys.executable, "-c", code], env=env, cwd=cwd, capture_output=True, text=True)
        if proc.returncode != 0:
            print(f"{name}: exit {proc.returncode}: {proc.stderr.strip().splitlines()[-1:]}", flush=True)
            continue
        digest = subprocess.run([sys.executable, "-c", DIGEST, str(run_dir / "checkpoint.pt")], env=env, cwd=cwd,
                                capture_output=True, text=True, check=True).stdout
        rows = (run_dir / "metrics.csv").read_text().splitlines()
        head = rows[0].split(",")
        keep = [i for i, h in enumerate(head) if h not in TIMING]
        metrics = [[r.split(",")[i] for i in keep] for r in rows]
        (out / f"{name}.json").write_text(json.dumps({"tensors": json.loads(digest), "metrics": metrics}))
        print(f"{name}: ok", flush=True)


def compare(a: Path, b: Path) -> int:
    bad = 0
    for name in CASES:
        fa, fb = a / f"{name}.json", b / f"{name}.json"
        if not (fa.exists() and fb.exists()):
            print(f"{name}: missing in {a if not fa.exists() else b}")
            bad += 1
            continue
        ja, jb = json.loads(fa.read_text()), json.loads(fb.read_text())
        diff = [k for k in sorted(set(ja["tensors"]) | set(jb["tensors"]))
                if ja["tensors"].get(k) != jb["tensors"].get(k)]
        same_metrics = ja["metrics"] == jb["metrics"]
        ok = not diff and same_metrics
        bad += not ok
        print(f"{name}: {'identical' if ok else 'DIFFERENT'} ({len(ja['tensors'])} tensors"
              f"{', differing: ' + ', '.join(diff[:5]) if diff else ''}"
              f"{'' if same_metrics else ', metrics differ'})")
    return 1 if bad else 0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("cmd", choices=("run", "compare"))
    p.add_argument("dirs", type=Path, nargs="+", help="run: OUT_DIR; compare: DIR_A DIR_B")
    p.add_argument("--pythonpath", help="run: the checkout whose code trains")
    args = p.parse_args()
    if len(args.dirs) != (1 if args.cmd == "run" else 2):
        p.error(f"{args.cmd} takes {'one folder' if args.cmd == 'run' else 'two folders'}")
    if args.cmd == "run":
        run(args.dirs[0], args.pythonpath)
    else:
        sys.exit(compare(*args.dirs))


if __name__ == "__main__":
    main()
