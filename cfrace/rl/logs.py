"""Training logs: metrics.csv (one row per iteration), TensorBoard scalars, the training-curve PNG."""

from __future__ import annotations

import csv
import math
from pathlib import Path

AGENT_NAMES = ("ego", "adversary")


class CsvLog:
    """metrics.csv with a header that grows when new metrics appear (the file is then rewritten).
    On resume, rows after the checkpoint's iteration are dropped (they will be recomputed)."""

    def __init__(self, path: Path, resume_iteration: int | None = None):
        self.path = Path(path)
        self.rows: list[dict] = []
        if resume_iteration is not None and self.path.exists():
            with self.path.open(newline="") as f:
                for row in csv.DictReader(f):
                    try:
                        if int(float(row["iteration"])) <= resume_iteration:
                            self.rows.append(dict(row))  # kept as text: rewritten byte for byte
                    except (KeyError, ValueError):
                        continue
        self.columns: list[str] = []
        for row in self.rows:
            self._extend(row)
        self._rewrite()

    def _extend(self, row: dict) -> bool:
        new = [k for k in row if k not in self.columns]
        self.columns += new
        return bool(new)

    def _rewrite(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".csv.tmp")
        with tmp.open("w", newline="") as f:
            w = csv.DictWriter(f, self.columns, restval="")
            w.writeheader()
            w.writerows(self.rows)
        tmp.replace(self.path)

    def write(self, row: dict) -> None:
        self.rows.append(dict(row))
        if self._extend(row) or len(self.rows) == 1:
            self._rewrite()
        else:
            with self.path.open("a", newline="") as f:
                csv.DictWriter(f, self.columns, restval="").writerow(row)


def _num(value) -> float:
    """A CSV cell or metric as float (NaN when empty or not a number)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def tb_tag(key: str) -> str:
    """Group CSV keys into TensorBoard sections."""
    if key.startswith("term_"):
        return f"terms/{key[5:]}"
    if key.startswith("stat_"):
        return f"race/{key[5:]}"
    if key.startswith(("reward_", "return_", "total_reward_")):
        return f"reward/{key}"
    if key.startswith(("surrogate", "value_loss", "entropy", "kl", "clip_frac", "samples")):
        return f"loss/{key}"
    if key in ("fps", "iter_s", "sim_s", "infer_s", "update_s", "wall_s"):
        return f"speed/{key}"
    return f"policy/{key}"


class TensorBoardLog:
    def __init__(self, log_dir: Path, purge_step: int | None = None):
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(log_dir=str(log_dir), purge_step=purge_step)

    def write(self, metrics: dict, step: int) -> None:
        for key, value in metrics.items():
            if key in ("iteration", "env_steps") or not isinstance(value, (int, float)) or math.isnan(value):
                continue
            self.writer.add_scalar(tb_tag(key), value, step)

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


def _ema(values: list[float], alpha: float) -> list[float]:
    out, acc = [], None
    for v in values:
        acc = v if acc is None else alpha * v + (1 - alpha) * acc
        out.append(acc)
    return out


def plot_training_curve(rows: list[dict], path: Path, title: str, num_agents: int) -> Path | None:
    """Episode return (cumulative reward) per drone against env steps, raw (faint) and smoothed.
    Falls back to the mean reward per step when no episode has finished yet. None if no rows."""
    if not rows:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    has_returns = any(not math.isnan(_num(r.get("return_agent0"))) for r in rows)
    key = "return_agent{}" if has_returns else "reward_agent{}"
    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    colours = ("tab:blue", "tab:red", "tab:green", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:gray")
    for a in range(num_agents):
        pts = [(_num(r["env_steps"]), _num(r.get(key.format(a)))) for r in rows]
        pts = [(x, y) for x, y in pts if not math.isnan(y)]
        if not pts:
            continue
        x, y = zip(*pts)
        label = (AGENT_NAMES[a] if a < len(AGENT_NAMES) else f"drone {a}") if num_agents > 1 else "agent"
        c = colours[a % len(colours)]
        ax.plot(x, y, color=c, alpha=0.25, linewidth=0.8)
        ax.plot(x, _ema(list(y), 0.1), color=c, linewidth=1.8, label=f"{label} (agent {a})")
    ax.set_ylabel("episode return (cumulative reward)" if has_returns else "mean reward per step")
    return finish_steps_plot(fig, ax, path, title)


def finish_steps_plot(fig, ax, path: Path, title: str = "", legend_size: float | None = None) -> Path:
    """Label the env-step axis, add grid, title and legend, save ``fig`` to ``path`` and close it."""
    import matplotlib.pyplot as plt

    ax.set_xlabel("environment steps (world transitions)")
    if title:
        ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=legend_size)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
