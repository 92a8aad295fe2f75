"""Learning per sample with a bf16 update against float32: DS on the lemniscate, several seeds each.

    python studies/training/precision_learning.py --out /tmp/prec --seeds 0 1 2 --steps 4000000

For every (precision, seed): `cfrace train --method ds --track lemniscate --precision P --steps N
--keep-checkpoints --checkpoint-min C`, then every kept checkpoint flies the single-agent
benchmark (`cfrace.reproduction.select.score_run`, --runs runs of 3 laps, seed 0). Writes OUT/scores.csv
(precision, seed, iteration, env steps, success, TTC) and OUT/precision_learning.png (success
against env steps, mean and spread over seeds per precision), and prints the first env-step count
at which each run reached 100 %. Resumable: finished runs and scored checkpoints are kept.
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
from pathlib import Path

import numpy as np

from cfrace.reproduction.select import score_run


def train(out: Path, precision: str, seed: int, steps: int, checkpoint_min: float) -> Path:
    run = out / f"ds_{precision}_s{seed}"
    if (run / "done").exists():
        return run
    cmd = ["cfrace", "train", "--method", "ds", "--track", "lemniscate", "--seed", str(seed), "--steps", str(steps),
           "--precision", precision, "--threads", "1", "--checkpoint-min", str(checkpoint_min), "--keep-checkpoints"]
    if (run / "checkpoint.pt").exists():
        cmd = ["cfrace", "train", "--resume", str(run), "--steps", str(steps), "--threads", "1",
               "--checkpoint-min", str(checkpoint_min)]
    else:
        cmd += ["--out", str(run)]
    with (out / f"{run.name}.log").open("a") as log:
        subprocess.run(cmd, check=True, stdout=log, stderr=subprocess.STDOUT)
    (run / "done").touch()
    return run


def first_full(rows: list[dict]) -> int | None:
    for r in rows:
        if r["success"] is not None and r["success"] >= 1.0:
            return r["env_steps"]
    return None


def plot(rows: list[dict], path: Path) -> None:
    """Success against env steps: each run faint, the mean and min-max spread over seeds
    (cfrace.rl.curves.mean_spread, the reproduction report's rule) per precision."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cfrace.rl.curves import mean_spread

    fig, ax = plt.subplots(figsize=(7, 4))
    for prec, color in (("fp32", "tab:blue"), ("bf16", "tab:orange")):
        curves = []
        for seed in sorted({r["seed"] for r in rows if r["precision"] == prec}):
            rs = [r for r in rows if r["precision"] == prec and r["seed"] == seed]
            curves.append({"env_steps": np.array([r["env_steps"] for r in rs], float),
                           "success": np.array([r["success"] for r in rs], float)})
            ax.plot(curves[-1]["env_steps"], curves[-1]["success"], color=color, alpha=0.25, lw=1)
        ms = mean_spread(curves, "success", points=60) if curves else None
        if ms is not None:
            grid, mean, lo, hi = ms
            ax.plot(grid, mean, color=color, lw=2, label=f"{prec} (mean of {len(curves)} seeds)")
            ax.fill_between(grid, lo, hi, color=color, alpha=0.15)
    ax.set_xlabel("env steps")
    ax.set_ylabel("success (3 laps, single-agent benchmark)")
    ax.set_title("DS on the lemniscate: bf16 update vs float32")
    ax.set_ylim(-0.02, 1.02)
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--steps", type=int, default=4_000_000)
    ap.add_argument("--checkpoint-min", type=float, default=0.5)
    ap.add_argument("--runs", type=int, default=20, help="benchmark runs per checkpoint")
    ap.add_argument("--points", type=int, default=24, help="checkpoints scored per run (evenly spaced)")
    ap.add_argument("--precisions", nargs="+", default=["fp32", "bf16"])
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in args.seeds:
        for prec in args.precisions:  # alternate, so that slow phases of the machine hit both
            run = train(args.out, prec, seed, args.steps, args.checkpoint_min)
            cached = run / "checkpoints" / "scores.csv"
            if cached.exists() and cached.stat().st_mtime > (run / "done").stat().st_mtime:
                with cached.open() as fh:  # scored by an earlier call
                    got = [{k: (float(v) if k in ("success", "lap_time_s") and v else int(v) if k in
                                ("iteration", "env_steps") else v or None) for k, v in r.items()}
                           for r in csv.DictReader(fh)]
            else:
                got = score_run(run, "lemniscate", runs=args.runs, laps=3, seed=0, max_points=args.points).rows
            rows += [{"precision": prec, "seed": seed, **r} for r in got]
            print(f"{prec} seed {seed}: first 100 % at {first_full(got)} env steps", flush=True)
    with (args.out / "scores.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, ["precision", "seed", "iteration", "env_steps", "success", "lap_time_s"],
                           extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    plot(rows, args.out / "precision_learning.png")
    for prec in args.precisions:
        firsts = [first_full([r for r in rows if r["precision"] == prec and r["seed"] == s]) for s in args.seeds]
        print(f"{prec}: first 100 % at {firsts} env steps")
    print(f"wrote {args.out / 'scores.csv'} and {args.out / 'precision_learning.png'}")


if __name__ == "__main__":
    sys.exit(main())
