"""Does a DS policy trained on the stand-recovered profile race like one trained on the true profile?

For each training seed S, RUNS/ds_true_sS and RUNS/ds_stand_sS hold the same DS training (equal env
steps) on the true profile (cf21bl) and on the recovered one (calibration/cf21bl_stand.yaml), each
with its checkpoint chosen on validation seed 100 (cfrace.reproduction.select.score_run, as
policies/pipeline.yaml does) in chosen.onnx. Every chosen policy is evaluated on the TRUE profile
on the test seeds (50 runs x 3 laps each, gate starts); the script prints one row per policy and
the means over the training seeds with their spread. Usage:

    .venv/bin/python studies/training/calibration_transfer.py --runs-dir runs/cal --seeds 2,3,4,5 [--json F]

The trainings (docs/calibration.md):

    cfrace train --preset cpu --threads 1 --method ds --track lemniscate --profile PROFILE \\
        --steps 6000000 --seed S --checkpoint-min 0.75 --keep-checkpoints --out RUNS/ds_{true,stand}_sS
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path


def main() -> None:
    from cfrace.evaluate.single import evaluate

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs-dir", required=True)
    ap.add_argument("--seeds", default="2,3,4,5", help="training seeds")
    ap.add_argument("--test-seeds", default="1,2,3")
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--profile", default="cf21bl", help="the true profile (evaluation)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    tests = [int(s) for s in args.test_seeds.split(",")]
    rows = []
    for seed in seeds:
        for kind in ("true", "stand"):
            onnx = Path(args.runs_dir) / f"ds_{kind}_s{seed}" / "chosen.onnx"
            success, laps, lap_sum = 0, 0, 0.0
            for t in tests:
                r = evaluate([str(onnx)], "lemniscate", False, args.runs, 3, t, None, args.profile, None).rows[0]
                success += round(r["success_rate"] * r["runs"])
                n_laps = r["laps_completed"]
                laps += n_laps
                lap_sum += r["lap_time_s"] * n_laps
            row = {"seed": seed, "profile": kind, "runs": args.runs * len(tests), "success": success,
                   "lap_time_s": lap_sum / max(laps, 1)}
            rows.append(row)
            print(f"seed {seed}  {kind:5}  success {success}/{row['runs']}  lap {row['lap_time_s']:.3f} s", flush=True)
    summary = {}
    for kind in ("true", "stand"):
        lap = [r["lap_time_s"] for r in rows if r["profile"] == kind]
        suc = [r["success"] / r["runs"] for r in rows if r["profile"] == kind]
        summary[kind] = {"lap_mean_s": statistics.mean(lap), "lap_sd_s": statistics.stdev(lap) if len(lap) > 1 else 0.0,
                         "success_mean": statistics.mean(suc), "success_min": min(suc)}
    diff = summary["stand"]["lap_mean_s"] / summary["true"]["lap_mean_s"] - 1.0
    print(f"\nmeans over {len(seeds)} training seeds: true lap {summary['true']['lap_mean_s']:.3f} s "
          f"(sd {summary['true']['lap_sd_s']:.3f}), success {100 * summary['true']['success_mean']:.1f} %; "
          f"recovered lap {summary['stand']['lap_mean_s']:.3f} s (sd {summary['stand']['lap_sd_s']:.3f}), "
          f"success {100 * summary['stand']['success_mean']:.1f} %; lap difference {100 * diff:+.1f} %")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "summary": summary, "lap_diff": diff,
                                               "test_seeds": tests}, indent=1) + "\n")


if __name__ == "__main__":
    main()
