"""Single-agent benchmark (paper Table I): every policy flies the same N start poses alone, all
policies and runs batched in one simulator (worlds = policies x runs, one drone each).

Multi-agent policies fly alone too; their opponent block shows an opponent that crashed at the start
(resting on the floor in the slot beside the drone's start, zero velocity: what a training race shows
once the opponent has crashed there), see cfrace.evaluate.rollout.parked_opponents.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cfrace.errors import ConfigError
from cfrace.evaluate.entrants import Entrant, common_profile, load_entrants, load_race_track
from cfrace.evaluate.metrics import solo_metrics
from cfrace.evaluate.plots import solo_trajectory_plots
from cfrace.evaluate.rollout import LAP_TIME_LIMIT_S, Recording, Starts, rollout, start_poses

PLOT_RUNS = 3  #: runs per policy whose positions are recorded for the trajectory plot


@dataclass
class SoloResult:
    track: str
    obstacles: bool
    runs: int
    laps: int
    seed: int
    time_limit_s: float
    rows: list[dict]                       #: one table row per policy (solo_metrics + name, path, method)
    recording: Recording | None = None
    plots: list[Path] = field(default_factory=list)
    wall_s: float = 0.0

    def to_json(self) -> dict:
        out = {"track": self.track, "obstacles": self.obstacles, "runs": self.runs, "laps": self.laps,
               "seed": self.seed, "time_limit_s": self.time_limit_s, "wall_s": round(self.wall_s, 3)}
        if len(self.rows) == 1:
            out.update({k: v for k, v in self.rows[0].items() if k not in out})
        out["policies"] = self.rows
        return out


def evaluate(policies: list[str], track_name: str, obstacles: bool = False, runs: int = 50, laps: int = 3,
             seed: int = 0, time_limit_s: float | None = None, profile: str | None = None,
             plot_dir: Path | None = None, threads: int | None = None, start: str = "gate") -> SoloResult:
    """Fly ``runs`` runs of ``laps`` laps per policy from the same random starts (``start``: "gate",
    before a random gate in the air, as the paper; "ground", on the floor before gate 0); the rows."""
    t0 = time.perf_counter()
    track = load_race_track(track_name, obstacles)
    entrants = load_entrants(policies, track, obstacles)
    prof = common_profile(entrants, profile)
    if runs < 1 or laps < 1:
        raise ConfigError("runs and laps must be >= 1")
    starts = start_poses(track, prof, runs, 1, obstacles, seed, start=start)
    p = len(entrants)
    rep = lambda x: x.repeat(p, *([1] * (x.dim() - 1)))          # (runs, ...) -> (p * runs, ...)
    all_starts = Starts(rep(starts.pos), rep(starts.quat), rep(starts.target))
    assign = np.repeat(np.arange(p), runs)[:, None]              # world k*runs + i: policy k, run i
    record = tuple(k * runs + i for k in range(p) for i in range(min(runs, PLOT_RUNS))) if plot_dir else ()
    limit = laps * LAP_TIME_LIMIT_S if time_limit_s is None else time_limit_s
    rec = rollout(track, prof, obstacles, entrants, assign, all_starts, laps, limit, record, seed, threads)
    summary = rec.summary()
    rows = []
    for k, e in enumerate(entrants):
        row = {"name": e.name, "path": str(e.path), "method": e.method, "obs_layout": e.layout.name,
               **solo_metrics(summary, slice(k * runs, (k + 1) * runs))}
        row["nan_action_steps"] = int(rec.nan_actions[k * runs:(k + 1) * runs].sum())
        rows.append(row)
    result = SoloResult(track.name, obstacles, runs, laps, seed, limit, rows, rec)
    if plot_dir is not None:
        result.plots = solo_trajectory_plots(plot_dir, track, obstacles, entrants, rec, summary, runs)
    result.wall_s = time.perf_counter() - t0
    return result


def _fmt(v, spec: str) -> str:
    return "–" if v is None else format(v, spec)


def markdown_table(result: SoloResult) -> str:
    """The rows as a markdown table shaped like the paper's Table I (plus the extra columns)."""
    title = (f"Single-agent benchmark, {result.track}{' with obstacles' if result.obstacles else ''}: "
             f"{result.runs} runs x {result.laps} lap{'s' if result.laps > 1 else ''}, seed {result.seed}, time limit {result.time_limit_s:g} s")
    head = ("| policy | method | Avg. TTC [s] | Avg. speed [m/s] | Collisions | Success [%] "
            "| best lap [s] | max speed [m/s] | crashes (reasons) | time-outs |")
    lines = [f"**{title}**", "", head, "|" + "---|" * 10]
    for r in result.rows:
        reasons = ", ".join(f"{k} {v}" for k, v in r["crash_reasons"].items())
        lines.append(f"| {r['name']} | {r['method']} | {_fmt(r['lap_time_s'], '.2f')} | "
                     f"{_fmt(r['avg_speed_mps'], '.2f')} | {r['collisions']} | {100 * r['success_rate']:.0f} | "
                     f"{_fmt(r['best_lap_s'], '.2f')} | {_fmt(r['max_speed_mps'], '.2f')} | "
                     f"{r['crashes']}{f' ({reasons})' if reasons else ''} | {r['timeouts']} |")
    lines += ["", "TTC: mean duration of all completed laps (the first timed from the start). Collisions: new "
              "obstacle/drone contacts plus gate-frame hits. Success: all laps without a terminal crash."]
    return "\n".join(lines) + "\n"
