"""How far do the sparse schemes get from scratch? Every kept checkpoint of a run, flown.

    .venv/bin/python benchmarks/scratch_progress.py RUN [RUN ...] [--runs 50] [--seed 1] [--every-min 10]
                                                    [--track lemniscate] [--agent ego|adversary]
                                                    [--json F] [--plot F.png]

For each run (``cfrace train --keep-checkpoints``, no --init-from: no dense reward in its history)
and each kept checkpoint about ``--every-min`` minutes of wall clock apart: the training's own
figures at that iteration (gates per second, the share of episodes that complete a lap and the
action std the rollouts sampled with, from RUN/metrics.csv, mean of the 5 logged iterations up to
it) and the exported actor (of a multi-agent run: ``--agent``, ego = agent 0 by default, or
adversary = agent 1) flown alone (``--runs`` runs of 3 laps, gate starts: success, laps completed
per run, time per lap) and, for a multi-agent run, against the shipped DS (``--runs``
races of 3 laps: win rate). One seed for every row: nothing is chosen here. Prints a markdown
table; ``--plot`` draws the training figures over env steps and over wall-clock minutes, and the
flown figures at the checkpoints.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from cfrace.rl.curves import near, training_figures


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


def progress(run: Path, track: str, runs: int, seed: int, every_min: float, agent: str = "ego") -> list[dict]:
    from cfrace.reproduction.select import kept_checkpoints, score_checkpoint
    from cfrace.rl.checkpoint import load_checkpoint

    rows = training_figures(run)
    ckpts = kept_checkpoints(run)
    multi = load_checkpoint(ckpts[0]).get("meta", {}).get("method") in ("ours", "dm")
    out = []
    for ckpt in spaced(ckpts, rows, every_min * 60.0):
        who = agent if multi else "best"
        alone = score_checkpoint(ckpt, track, False, None, runs, 3, seed, who)
        it = alone["iteration"]
        row = {"run": run.name, "iteration": it, "env_steps": alone["env_steps"], "wall_min": alone["wall_min"],
               "gates_per_s": round(near(rows, it, "gates_per_s"), 3), "lap_share": round(near(rows, it, "lap_share"), 3),
               "std": round(near(rows, it, "std1" if who == "adversary" else "std"), 3), "success": alone["success"],
               "laps_per_run": alone["laps_per_run"], "lap_time_s": alone["lap_time_s"]}
        if multi:
            row["win_rate_vs_ds"] = score_checkpoint(ckpt, track, False, "ds", runs, 3, seed, who)["win_rate"]
        out.append(row)
        vs = f" | {row['win_rate_vs_ds']:.0%}" if multi else " | –"
        ttc = "–" if row["lap_time_s"] is None else f"{row['lap_time_s']:.2f}"
        print(f"| {run.name} | {row['wall_min']:.0f} | {row['env_steps'] / 1e6:.1f} | {row['std']:.2f} | "
              f"{row['gates_per_s']:.2f} | {row['lap_share']:.0%} | {row['success']:.0%} | {row['laps_per_run']:.2f} | "
              f"{ttc}{vs} |", flush=True)
    return out


def plot(path: Path, runs: list[Path], table: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5))
    (ax0, ax1), (ax2, ax3) = axes
    for k, run in enumerate(runs):
        rows, colour = training_figures(run), f"C{k}"
        steps = [r["env_steps"] / 1e6 for r in rows]
        ax0.plot(steps, [r["gates_per_s"] for r in rows], label=run.name, lw=0.8, color=colour)
        ax1.plot(steps, [r["lap_share"] for r in rows], label=run.name, lw=0.8, color=colour)
        ax2.plot([r["wall_s"] / 60.0 for r in rows], [r["lap_share"] for r in rows], label=run.name, lw=0.8,
                 color=colour)
        mine = [r for r in table if r["run"] == run.name]
        at = [r["env_steps"] / 1e6 for r in mine]
        ax3.plot(at, [r["success"] for r in mine], "o-", color=colour, label=f"{run.name}: success (3 laps)")
        ax3.plot(at, [r["laps_per_run"] / 3.0 for r in mine], "^:", color=colour, label=f"{run.name}: laps / 3")
        if mine and "win_rate_vs_ds" in mine[0]:
            ax3.plot(at, [r["win_rate_vs_ds"] for r in mine], "s--", color=colour, label=f"{run.name}: win rate vs DS")
    ax0.set(xlabel="env steps (M)", ylabel="gates per second", title="training episodes: gates per second")
    ax1.set(xlabel="env steps (M)", ylabel="share of episodes", ylim=(-0.02, 1.02),
            title="training episodes with a lap, over env steps")
    ax2.set(xlabel="wall clock (min)", ylabel="share of episodes", ylim=(-0.02, 1.02),
            title="training episodes with a lap, over wall clock")
    ax3.set(xlabel="env steps (M)", ylabel="share", ylim=(-0.05, 1.05), title="checkpoints flown alone (mean action)")
    for ax in axes.flat:
        ax.legend(fontsize=8)
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
    ap.add_argument("--agent", default="ego", choices=("ego", "adversary"),
                    help="which agent of a multi-agent run is flown")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--plot", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    print("| run | wall min | env steps (M) | action std | gates/s (training) | episodes with a lap | success alone | "
          "laps per run alone | s per lap | win rate vs DS |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    table = [row for run in args.runs for row in progress(run, args.track, args.n, args.seed, args.every_min, args.agent)]
    if args.json is not None:
        args.json.write_text(json.dumps({"seed": args.seed, "runs_per_point": args.n, "rows": table}, indent=1))
    if args.plot is not None:
        plot(args.plot, args.runs, table)


if __name__ == "__main__":
    main()
