"""How far do the sparse schemes get from scratch? Every kept checkpoint of a run, flown.

    .venv/bin/python benchmarks/scratch_progress.py RUN [RUN ...] [--runs 50] [--seed 1] [--every-min 10]
                                                    [--track lemniscate] [--json F] [--plot F.png]

For each run (``cfrace train --keep-checkpoints``, no --init-from: no dense reward in its history)
and each kept checkpoint about ``--every-min`` minutes of wall clock apart: the training's own
figures at that iteration (gates per second and the share of episodes that complete a lap, from
RUN/metrics.csv, mean of the 5 logged iterations up to it) and the exported actor flown alone
(``--runs`` runs of 3 laps, gate starts: success, time per lap) and, for a multi-agent run,
against the shipped DS (``--runs`` races of 3 laps: win rate). One seed for every row: nothing is
chosen here. Prints a markdown table; ``--plot`` draws gates per second over env steps and the
flown figures at the checkpoints.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import torch


def training_figures(run: Path) -> list[dict]:
    """RUN/metrics.csv rows as floats (iteration, env_steps, wall_s, gates/s, lap share)."""
    with (run / "metrics.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    keys = {"iteration": "iteration", "env_steps": "env_steps", "wall_s": "wall_s",
            "gates_per_s": "stat_gates_per_s", "lap_share": "stat_success"}
    out = []
    for r in rows:
        try:
            out.append({k: float(r[v]) for k, v in keys.items()})
        except (KeyError, ValueError):
            continue
    return out


def near(rows: list[dict], iteration: int, key: str, n: int = 5) -> float:
    """Mean of ``key`` over the n logged iterations up to ``iteration``."""
    mine = [r[key] for r in rows if r["iteration"] <= iteration][-n:]
    return sum(mine) / len(mine) if mine else float("nan")


def spaced(ckpts: list[Path], rows: list[dict], every_s: float) -> list[Path]:
    """Checkpoints at least every_s of wall clock apart (the first and the last always)."""
    wall = {int(r["iteration"]): r["wall_s"] for r in rows}
    out, last = [], -1e9
    for c in ckpts:
        t = wall.get(int("".join(ch for ch in c.stem if ch.isdigit()) or 0), last + every_s)
        if t - last >= every_s or c == ckpts[-1]:
            out.append(c)
            last = t
    return out


def progress(run: Path, track: str, runs: int, seed: int, every_min: float) -> list[dict]:
    from cfrace.evaluate.select import kept_checkpoints, score_checkpoint
    from cfrace.rl.checkpoint import load_checkpoint

    rows = training_figures(run)
    ckpts = kept_checkpoints(run)
    multi = load_checkpoint(ckpts[0]).get("meta", {}).get("method") in ("ours", "dm")
    out = []
    for ckpt in spaced(ckpts, rows, every_min * 60.0):
        alone = score_checkpoint(ckpt, track, False, None, runs, 3, seed, "ego" if multi else "best")
        it = alone["iteration"]
        row = {"run": run.name, "iteration": it, "env_steps": alone["env_steps"], "wall_min": alone["wall_min"],
               "gates_per_s": round(near(rows, it, "gates_per_s"), 3), "lap_share": round(near(rows, it, "lap_share"), 3),
               "success": alone["success"], "lap_time_s": alone["lap_time_s"]}
        if multi:
            row["win_rate_vs_ds"] = score_checkpoint(ckpt, track, False, "ds", runs, 3, seed, "ego")["win_rate"]
        out.append(row)
        vs = f" | {row['win_rate_vs_ds']:.0%}" if multi else " | –"
        ttc = "–" if row["lap_time_s"] is None else f"{row['lap_time_s']:.2f}"
        print(f"| {run.name} | {row['wall_min']:.0f} | {row['env_steps'] / 1e6:.1f} | {row['gates_per_s']:.2f} | "
              f"{row['lap_share']:.0%} | {row['success']:.0%} | {ttc}{vs} |", flush=True)
    return out


def plot(path: Path, runs: list[Path], table: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4))
    for run in runs:
        rows = training_figures(run)
        ax0.plot([r["env_steps"] / 1e6 for r in rows], [r["gates_per_s"] for r in rows], label=run.name, lw=0.8)
        mine = [r for r in table if r["run"] == run.name]
        ax1.plot([r["env_steps"] / 1e6 for r in mine], [r["success"] for r in mine], "o-", label=f"{run.name}: success alone")
        if mine and "win_rate_vs_ds" in mine[0]:
            ax1.plot([r["env_steps"] / 1e6 for r in mine], [r["win_rate_vs_ds"] for r in mine], "s--",
                     label=f"{run.name}: win rate vs DS")
    ax0.set(xlabel="env steps (M)", ylabel="gates per second (training episodes)", title="from scratch: training")
    ax1.set(xlabel="env steps (M)", ylabel="share of 50", ylim=(-0.05, 1.05), title="checkpoints flown (3 laps)")
    ax0.legend()
    ax1.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--track", default="lemniscate")
    ap.add_argument("--runs", dest="n", type=int, default=50)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--every-min", type=float, default=10.0)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--plot", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    print("| run | wall min | env steps (M) | gates/s (training) | episodes with a lap | success alone | s per lap | win rate vs DS |")
    print("|---|---|---|---|---|---|---|---|")
    table = [row for run in args.runs for row in progress(run, args.track, args.n, args.seed, args.every_min)]
    if args.json is not None:
        args.json.write_text(json.dumps({"seed": args.seed, "runs_per_point": args.n, "rows": table}, indent=1))
    if args.plot is not None:
        plot(args.plot, args.runs, table)


if __name__ == "__main__":
    main()
