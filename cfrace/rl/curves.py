"""Training curves over several runs: small CSVs kept with the shipped policies, and the plot of
their mean and spread (the paper's training-curve figures: mean over seeds, shaded spread).

A curve CSV is a run's metrics.csv reduced to CURVE_COLUMNS and at most MAX_ROWS rows (evenly
spaced), so that a fresh clone can draw the figures without the runs. `reduce_metrics` writes one,
`plot_curves` draws groups of them.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from cfrace.rl.logs import finish_steps_plot

CURVE_COLUMNS = ("env_steps", "wall_s", "return_agent0", "return_agent1", "stat_gates_per_s", "stat_success",
                 "stat_crash_rate", "stat_lap_time_s", "stat_win_share_agent0")
#: kept too when the run has it (a run with --obstacle-curriculum: the obstacles' size per iteration)
OPTIONAL_COLUMNS = ("stat_obstacle_scale",)
MAX_ROWS = 200
#: what plot_curves can draw: column -> axis label
LABELS = {"return_agent0": "episode return (drone 0)", "stat_gates_per_s": "gates per second (training races)",
          "stat_success": "share of races with a lap done", "stat_lap_time_s": "lap time [s]"}


def _num(text) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


def read_curve(path: Path) -> dict[str, np.ndarray]:
    """Columns of a curve (or metrics) CSV as float arrays (missing values NaN)."""
    with Path(path).open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    keys = rows[0].keys() if rows else CURVE_COLUMNS
    return {k: np.array([_num(r.get(k)) for r in rows]) for k in keys}


def reduce_metrics(metrics_csv: Path, out: Path, offset_steps: int = 0, max_rows: int = MAX_ROWS) -> Path:
    """Write ``metrics_csv`` reduced to CURVE_COLUMNS (and the OPTIONAL_COLUMNS it has) and at most
    ``max_rows`` rows; ``offset_steps`` is added to env_steps (a warm-started stage continues its
    source's count)."""
    with Path(metrics_csv).open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    columns = CURVE_COLUMNS + tuple(k for k in OPTIONAL_COLUMNS if any(r.get(k) for r in rows))
    if len(rows) > max_rows:
        keep = np.unique(np.linspace(0, len(rows) - 1, max_rows).round().astype(int))
        rows = [rows[i] for i in keep]
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("w", newline="") as fh:
        w = csv.DictWriter(fh, columns, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            r = dict(r)
            r["env_steps"] = str(int(_num(r.get("env_steps")) + offset_steps))
            w.writerow({k: r.get(k, "") for k in columns})
    return out


def mean_spread(curves: list[dict[str, np.ndarray]], y: str, points: int = 100):
    """(x grid, mean, min, max) of column ``y`` over curves interpolated on a common env-step grid
    (up to the shortest run, so that every point has every seed)."""
    pairs = []
    for c in curves:
        ok = ~np.isnan(c.get(y, np.full_like(c["env_steps"], np.nan)))
        if ok.sum() >= 2:
            pairs.append((c["env_steps"][ok], c[y][ok]))
    if not pairs:
        return None
    end = min(x[-1] for x, _ in pairs)
    start = max(x[0] for x, _ in pairs)
    grid = np.linspace(start, end, points) if end > start else np.array([start])
    ys = np.array([np.interp(grid, x, v) for x, v in pairs])
    return grid, ys.mean(0), ys.min(0), ys.max(0)


def plot_curves(groups: dict[str, list[Path]], path: Path, y: str = "return_agent0", title: str = "") -> Path | None:
    """One line per group (mean over its CSVs) with the min-max spread shaded; None if nothing to draw."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    drawn = 0
    for label, files in groups.items():
        ms = mean_spread([read_curve(f) for f in files], y)
        if ms is None:
            continue
        grid, mean, lo, hi = ms
        line, = ax.plot(grid, mean, lw=1.8, label=f"{label} ({len(files)} run{'s' if len(files) > 1 else ''})")
        if len(files) > 1:
            ax.fill_between(grid, lo, hi, color=line.get_color(), alpha=0.2)
        drawn += 1
    if not drawn:
        plt.close(fig)
        return None
    ax.set_ylabel(LABELS.get(y, y))
    return finish_steps_plot(fig, ax, path, title, legend_size=8)


def training_figures(run: Path) -> list[dict]:
    """RUN/metrics.csv rows as floats (iteration, env_steps, wall_s, gates/s, lap share)."""
    with (run / "metrics.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    keys = {"iteration": "iteration", "env_steps": "env_steps", "wall_s": "wall_s",
            "gates_per_s": "stat_gates_per_s", "lap_share": "stat_success", "std": "std_agent0"}
    out = []
    for r in rows:
        try:
            row = {k: float(r[v]) for k, v in keys.items()}
            row["std1"] = float(r.get("std_agent1") or row["std"])   # agent 1's (a single-agent run: agent 0's)
        except (KeyError, ValueError):
            continue
        out.append(row)
    return out


def near(rows: list[dict], iteration: int, key: str, n: int = 5) -> float:
    """Mean of ``key`` over the n logged iterations up to ``iteration``."""
    mine = [r[key] for r in rows if r["iteration"] <= iteration][-n:]
    return sum(mine) / len(mine) if mine else float("nan")
