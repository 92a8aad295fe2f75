"""Training curves of several runs combined: mean and spread over seeds, one line per group.

plot_seed_curves(groups, path) is the general function (groups: label -> list of metrics.csv row
lists); sweep_curves(sweep, out_root, path) feeds it the runs of a sweep grouped by everything
but their seed (Sweep.groups).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from cfrace.rl.logs import _ema, _num
from cfrace.sweep.spec import Sweep

PANELS = (("return_agent0", "episode return, agent 0"), ("stat_success", "share of races with >= 1 lap"))
GRID_POINTS = 100


def read_rows(path: Path) -> list[dict]:
    """Rows of a metrics.csv ([] when missing)."""
    import csv

    if not path.exists():
        return []
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def seed_band(runs_rows: list[list[dict]], key: str, smooth: float = 0.1) -> tuple[np.ndarray, ...] | None:
    """(x, mean, low, high): each run's smoothed curve of ``key`` against env steps, interpolated on
    a common grid up to the shortest run; low/high = mean -+ one standard deviation over runs (the
    single curve with one run). None when no run has a value."""
    curves = []
    for rows in runs_rows:
        pts = [(_num(r.get("env_steps")), _num(r.get(key))) for r in rows]
        pts = [(x, y) for x, y in pts if not (math.isnan(x) or math.isnan(y))]
        if pts:
            x, y = zip(*pts)
            curves.append((np.asarray(x), np.asarray(_ema(list(y), smooth))))
    if not curves:
        return None
    lo, hi = max(c[0][0] for c in curves), min(c[0][-1] for c in curves)
    grid = np.linspace(lo, hi, GRID_POINTS) if hi > lo else np.asarray([hi])
    ys = np.stack([np.interp(grid, x, y) for x, y in curves])
    mean, std = ys.mean(0), ys.std(0)
    return grid, mean, mean - std, mean + std


def plot_seed_curves(groups: dict[str, list[list[dict]]], path: Path, title: str = "",
                     panels: tuple[tuple[str, str], ...] = PANELS) -> Path | None:
    """One panel per metric, one line per group (mean over its runs) with a band of -+ one std."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4), dpi=120, squeeze=False)
    drawn = False
    for ax, (key, label) in zip(axes[0], panels):
        for i, (name, runs_rows) in enumerate(groups.items()):
            band = seed_band(runs_rows, key)
            if band is None:
                continue
            x, mean, low, high = band
            colour = f"C{i % 10}"
            n = sum(1 for rows in runs_rows if rows)
            ax.plot(x, mean, color=colour, linewidth=1.8, label=f"{name} ({n} seed{'s' if n != 1 else ''})")
            ax.fill_between(x, low, high, color=colour, alpha=0.2, linewidth=0)
            drawn = True
        ax.set_xlabel("environment steps (world transitions)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize=8)
    if drawn:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.suptitle(title or "training curves: mean over seeds, band = -+ 1 std")
        fig.tight_layout()
        fig.savefig(path)
    plt.close(fig)
    return Path(path) if drawn else None


def sweep_curves(sweep: Sweep, out_root: str | Path, path: Path | None = None) -> Path | None:
    """OUT/curves.png (or ``path``): the sweep's runs grouped by everything but the seed."""
    groups = {label: [read_rows(r.out_dir(out_root) / "metrics.csv") for r in runs]
              for label, runs in sweep.groups().items()}
    return plot_seed_curves(groups, Path(path) if path else Path(out_root) / "curves.png",
                            f"{Path(sweep.path).stem}: mean over seeds, band = -+ 1 std")
