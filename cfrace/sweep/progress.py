"""What a run is doing, read from its folder (metrics.csv), and the rich table of all runs."""

from __future__ import annotations

import csv
import io
import math
import time
from dataclasses import dataclass
from pathlib import Path

from rich.markup import escape
from rich.table import Table

from cfrace.sweep.spec import Run

STATE_STYLE = {"done": "green", "running": "cyan", "waiting": "dim", "queued": "dim", "failed": "red",
               "blocked": "yellow", "retrying": "magenta"}


def last_row(path: Path, tail_bytes: int = 16384) -> dict | None:
    """The last complete row of a metrics.csv (header + last line), or None."""
    try:
        with open(path, "rb") as fh:
            header = fh.readline().decode()
            fh.seek(0, io.SEEK_END)
            size = fh.tell()
            fh.seek(max(len(header), size - tail_bytes))
            lines = fh.read().decode(errors="replace").splitlines()
    except OSError:
        return None
    lines = [ln for ln in lines if ln.strip()]
    if not header or not lines:
        return None
    rows = list(csv.DictReader([header, lines[-1]]))
    return rows[0] if rows and None not in rows[0].values() else None


def _float(row: dict | None, key: str) -> float:
    try:
        return float(row[key]) if row and row.get(key) not in (None, "") else math.nan
    except ValueError:
        return math.nan


@dataclass
class RunState:
    """The driver's view of one run."""

    run: Run
    state: str = "waiting"      #: waiting | queued | running | retrying | done | failed | blocked
    attempts: int = 0
    submitted: float = 0.0      #: time.time() of the last submission
    started_s: float | None = None  #: time.time() the current attempt started working (its log grew)
    wall_s: float = 0.0         #: the run's own time in this sweep (all attempts, without queueing)
    action: str = ""            #: start | resume | skip | export
    error: str | None = None

    def poll_started(self, out_root: str | Path) -> None:
        """queued -> running once the task has written to the run's train.log."""
        try:
            mtime = (self.run.out_dir(out_root) / "train.log").stat().st_mtime
        except OSError:
            return
        if mtime >= self.submitted - 1.0:
            self.state = "running" if self.attempts == 1 else "retrying"
            self.started_s = time.time()

    def progress(self, out_root: str | Path) -> dict:
        """Iteration, env steps, share of the budget and last returns, from metrics.csv."""
        row = last_row(self.run.out_dir(out_root) / "metrics.csv")
        steps, wall = _float(row, "env_steps"), _float(row, "wall_s")
        parts = []
        if self.run.steps is not None and not math.isnan(steps):
            parts.append(steps / self.run.steps)
        if self.run.minutes is not None and not math.isnan(wall):
            parts.append(wall / (60.0 * self.run.minutes))
        share = 1.0 if self.state == "done" else (min(1.0, max(parts)) if parts else 0.0)
        return {"iteration": _float(row, "iteration"), "env_steps": steps, "share": share,
                "fps": _float(row, "fps"), "return": _float(row, "return_agent0"),
                "success": _float(row, "stat_success")}


def _n(v: float, spec: str) -> str:
    return "-" if math.isnan(v) else format(v, spec)


def progress_table(states: list[RunState], out_root: str | Path, title: str = "") -> Table:
    """One row per run: state, attempt, iteration, env steps, budget bar, steps/s, return, laps done."""
    t = Table(title=title, title_justify="left", header_style="bold")
    for col, just in (("run", "left"), ("state", "left"), ("try", "right"), ("it", "right"),
                      ("env steps", "right"), ("budget", "left"), ("steps/s", "right"), ("return", "right"),
                      ("lap done", "right"), ("time", "right")):
        t.add_column(col, justify=just)
    now = time.time()
    for s in states:
        p = s.progress(out_root)
        bar = "#" * int(round(p["share"] * 12))
        wall = s.wall_s + (now - s.started_s if s.started_s is not None else 0.0)
        style = STATE_STYLE.get(s.state, "")
        state = f"[{style}]{s.state}[/{style}]" if style else s.state
        if s.error and s.state in ("failed", "retrying"):
            state += f" [dim]({escape(s.error)})[/dim]"
        t.add_row(escape(s.run.name), state, str(s.attempts or "-"), _n(p["iteration"], ".0f"), _n(p["env_steps"], ",.0f"),
                  f"{bar:<12} {p['share']:4.0%}", _n(p["fps"], ",.0f"), _n(p["return"], ".3g"),
                  _n(p["success"], ".0%"), f"{wall:.0f} s" if wall else "-")
    return t
