"""A sweep's combined training curves: its runs grouped by everything but the seed (Sweep.groups),
drawn by the reproduction report's code (cfrace.rl.curves.plot_curves: mean over seeds, min-max
spread shaded), straight from each run's metrics.csv."""

from __future__ import annotations

from pathlib import Path

from cfrace.rl.curves import plot_curves
from cfrace.sweep.spec import Sweep

#: file suffix -> metrics.csv column drawn
FIGURES = {"": "return_agent0", "_success": "stat_success"}


def sweep_curves(sweep: Sweep, out_root: str | Path, path: Path | None = None) -> list[Path]:
    """OUT/curves.png (episode return of drone 0) and OUT/curves_success.png (share of training
    races with a lap); ``path`` renames the first (the second gets the _success suffix)."""
    groups = {}
    for label, runs in sweep.groups().items():
        files = [r.out_dir(out_root) / "metrics.csv" for r in runs]
        files = [f for f in files if f.exists() and f.stat().st_size > 0]
        if files:
            groups[label] = files
    base = Path(path) if path else Path(out_root) / "curves.png"
    written = []
    for suffix, column in FIGURES.items():
        target = base.with_name(base.stem + suffix + base.suffix)
        title = f"{Path(sweep.path).stem}: mean over seeds, min-max shaded"
        p = plot_curves(groups, target, column, title) if groups else None
        if p is not None:
            written.append(p)
    return written
