"""`cfrace sim robustness`: policies through the lockstep flight stack over a grid of lab conditions.

Each cell of the grid (mocap latency x drone profile x mocap noise) runs, for every seed, the
lockstep dry-run that `cfrace sim dry-run --lockstep` and `cfrace fly` run (cfrace.rehearsal.dryrun):

- alone: each policy flies ``laps`` laps with the other one stopped at once
  (``--faults nan_policy@0.02:opp``, it lies at its start): laps flown, how the run ended
  (crashes by cause: the flight stack's stop kind), mean lap time;
- head to head: the two race each other, slots swapped every other race: who wins.

The estimator's forward prediction follows the dry-run's default (as much as the simulated latency)
unless ``comp_ms`` fixes it; ``firmware_idle`` flies each profile at its firmware's idle thrust. The result (rows, per-cell summaries) goes to JSON, a markdown table
and a heat map; `cfrace reproduce` puts a grid of it in its report.
"""

from __future__ import annotations

import itertools
import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from cfrace.errors import ConfigError

STOP_AT_ONCE = "nan_policy@0.02:opp"   #: the alone runs' fault: the opponent's policy fails at 20 ms
QUICK = dict(latencies_ms=(0.0, 20.0), noise_mm=(1.0,), seeds=(1,), laps=1, duels=1)   #: the CI-size grid


@dataclass(frozen=True)
class Grid:
    track: str = "lemniscate"
    ego: str = "ours"
    opp: str = "ds"
    latencies_ms: tuple[float, ...] = (0.0, 10.0, 20.0, 30.0)
    profiles: tuple[str, ...] = ("cf2x_paper", "cf21bl")
    noise_mm: tuple[float, ...] = (1.0, 3.0)
    seeds: tuple[int, ...] = (1, 2, 3)
    laps: int = 2
    duels: int = 2              #: head-to-head races per seed and cell (slots swapped every other one)
    alone: bool = True
    comp_ms: float | None = None   #: latency compensation; None: the dry-run's default (= the latency)
    timeout_s: float = 60.0
    #: each profile flies with its firmware's powerDist.idleThrust (cfrace.loopmodel.IDLE_THRUST_COUNTS:
    #: the Brushless 7000 counts); off: the simulator's default (0, docs/simcf.md "Idle thrust")
    firmware_idle: bool = False

    def check(self) -> "Grid":
        from cfrace.drone import load_profile
        from cfrace.track import load_track
        if not self.latencies_ms or any(not 0.0 <= v <= 100.0 for v in self.latencies_ms):
            raise ConfigError(f"--latencies-ms: values in [0, 100] ms, got {list(self.latencies_ms)}")
        if not self.noise_mm or any(not 0.0 <= v <= 50.0 for v in self.noise_mm):
            raise ConfigError(f"--noise-mm: values in [0, 50] mm, got {list(self.noise_mm)}")
        if not self.seeds:
            raise ConfigError("--seeds: at least one seed")
        if self.laps < 1 or self.duels < 0:
            raise ConfigError("--laps must be >= 1 and --duels >= 0")
        if self.comp_ms is not None and not 0.0 <= self.comp_ms < 100.0:
            raise ConfigError(f"--comp-ms: in [0, 100) ms, got {self.comp_ms:g}")
        for p in self.profiles:
            try:
                load_profile(p)
            except ConfigError as exc:
                raise ConfigError(f"--profiles: {exc}") from None
        load_track(self.track)
        return self

    def quick(self) -> "Grid":
        """The same grid at CI size (`--quick`): latencies 0 and 20 ms, 1 mm noise, one seed, one lap, one race."""
        return replace(self, **QUICK)

    @property
    def cells(self):
        return list(itertools.product(self.latencies_ms, self.profiles, self.noise_mm))


def _config(grid: Grid, ego: str, opp: str, profile: str, latency_ms: float):
    from cfrace.flight.config import FlightConfig
    comp = latency_ms if grid.comp_ms is None else grid.comp_ms
    return FlightConfig(track=grid.track, ego=ego, opp=opp, laps=grid.laps, profile=profile, quiet=True,
                        rt_priority=0, loop_cpu="off", latency_comp_s=comp / 1e3, timeout_s=grid.timeout_s)


def _idle(grid: Grid, profile: str) -> int | None:
    """The idle thrust (counts) the grid's drones of ``profile`` boot with; None: the simulator's default."""
    from cfrace.loopmodel import IDLE_THRUST_COUNTS
    return int(IDLE_THRUST_COUNTS.get(profile, 0)) if grid.firmware_idle else None


def alone_run(grid: Grid, policy: str, other: str, latency_ms: float, profile: str, noise_mm: float, seed: int) -> dict:
    """``policy`` alone (the other stopped at once) through the lockstep stack."""
    from cfrace.rehearsal.dryrun import dry_run
    res = dry_run(_config(grid, policy, other, profile, latency_ms), lockstep=True, faults=STOP_AT_ONCE, seed=seed,
                  mocap_noise_m=noise_mm / 1e3, mocap_latency_s=latency_ms / 1e3, idle_thrust=_idle(grid, profile)).to_json()
    d = res["drones"][0]
    laps = int(d["laps"])
    times = res["lap_times"].get("ego") or []
    return {"kind": "alone", "policy": policy, "latency_ms": latency_ms, "profile": profile, "noise_mm": noise_mm,
            "seed": seed, "laps": min(laps, grid.laps), "finished": laps >= grid.laps,
            "end": "finished" if laps >= grid.laps else (d.get("stop_kind") or res["end"]),
            "lap_s": sum(times) / len(times) if times else None, "speed_mps": d.get("speed_mean")}


def duel_run(grid: Grid, k: int, latency_ms: float, profile: str, noise_mm: float, seed: int) -> dict:
    """Race k of a cell: ego and opp swap slots every other race; the winner by the flight stack."""
    from cfrace.rehearsal.dryrun import dry_run
    first, second = (grid.ego, grid.opp) if k % 2 == 0 else (grid.opp, grid.ego)
    res = dry_run(_config(grid, first, second, profile, latency_ms), lockstep=True, seed=seed * 1000 + k,
                  mocap_noise_m=noise_mm / 1e3, mocap_latency_s=latency_ms / 1e3, idle_thrust=_idle(grid, profile)).to_json()
    names = {"ego": first, "opp": second}
    winner = names.get(res["winner"]) if res["winner"] else None
    return {"kind": "duel", "latency_ms": latency_ms, "profile": profile, "noise_mm": noise_mm, "seed": seed,
            "race": k, "ego_slot": "ego" if first == grid.ego else "opp", "winner": winner, "end": res["end"],
            "laps": {names[s]: int(v) for s, v in res["laps"].items()}}


def summarise(grid: Grid, rows: list[dict]) -> list[dict]:
    """Per cell: per policy laps flown / attempted, crashes by cause, mean lap time; ego's win share."""
    cells = []
    for lat, prof, noise in grid.cells:
        mine = [r for r in rows if (r["latency_ms"], r["profile"], r["noise_mm"]) == (lat, prof, noise)]
        cell = {"latency_ms": lat, "profile": prof, "noise_mm": noise, "alone": {}}
        for pol in (grid.ego, grid.opp):
            runs = [r for r in mine if r["kind"] == "alone" and r["policy"] == pol]
            if not runs:
                continue
            ends: dict[str, int] = {}
            for r in runs:
                if not r["finished"]:
                    ends[r["end"]] = ends.get(r["end"], 0) + 1
            laps = [r["lap_s"] for r in runs if r["lap_s"] is not None]
            cell["alone"][pol] = {"runs": len(runs), "laps": sum(r["laps"] for r in runs),
                                  "of": grid.laps * len(runs), "lap_share": sum(r["laps"] for r in runs) / (grid.laps * len(runs)),
                                  "failures": ends, "lap_s": sum(laps) / len(laps) if laps else None}
        duels = [r for r in mine if r["kind"] == "duel"]
        if duels:
            wins = sum(r["winner"] == grid.ego for r in duels)
            cell["duel"] = {"races": len(duels), "ego_wins": wins,
                            "opp_wins": sum(r["winner"] == grid.opp for r in duels), "ego_win_share": wins / len(duels)}
        cells.append(cell)
    return cells


def run_grid(grid: Grid, on_progress=None) -> dict:
    """Every run of the grid, sequentially (each is deterministic in its seed); the result dict."""
    grid.check()
    say = on_progress or (lambda text: None)
    rows, t0 = [], time.perf_counter()
    for lat, prof, noise in grid.cells:
        for seed in grid.seeds:
            if grid.alone:
                rows.append(alone_run(grid, grid.ego, grid.opp, lat, prof, noise, seed))
                rows.append(alone_run(grid, grid.opp, grid.ego, lat, prof, noise, seed))
            for k in range(grid.duels):
                rows.append(duel_run(grid, k, lat, prof, noise, seed))
        say(f"latency {lat:g} ms, {prof}, noise {noise:g} mm: done ({time.perf_counter() - t0:.0f} s)")
    return {"grid": asdict(grid), "rows": rows, "cells": summarise(grid, rows),
            "wall_s": round(time.perf_counter() - t0, 1)}


def _profile_label(g: dict, profile: str) -> str:
    """The profile's name, with its idle thrust when the grid flew the firmware's."""
    from cfrace.loopmodel import IDLE_THRUST_COUNTS
    idle = IDLE_THRUST_COUNTS.get(profile) if g.get("firmware_idle") else None
    return f"{profile} (idle {idle:.0f})" if idle else profile


def markdown_table(result: dict) -> str:
    """One line per cell: laps flown alone per policy (with failures) and the ego's win share."""
    g = result["grid"]
    ego, opp = g["ego"], g["opp"]
    lines = [f"| latency ms | profile | noise mm | {ego} alone laps | {opp} alone laps | {ego} lap s | "
             f"{opp} lap s | {ego} wins |", "|---|---|---|---|---|---|---|---|"]

    def laps(c, p):
        a = c["alone"].get(p)
        if a is None:
            return "-"
        fails = ", ".join(f"{k} {v}" for k, v in sorted(a["failures"].items()))
        return f"{a['laps']}/{a['of']}" + (f" ({fails})" if fails else "")

    def lap_s(c, p):
        a = c["alone"].get(p)
        return f"{a['lap_s']:.2f}" if a and a["lap_s"] is not None else "-"

    for c in result["cells"]:
        d = c.get("duel")
        win = f"{d['ego_wins']}/{d['races']}" if d else "-"
        lines.append(f"| {c['latency_ms']:g} | {_profile_label(g, c['profile'])} | {c['noise_mm']:g} | {laps(c, ego)} | {laps(c, opp)} | "
                     f"{lap_s(c, ego)} | {lap_s(c, opp)} | {win} |")
    return "\n".join(lines) + "\n"


def heatmap(result: dict, path: Path) -> Path:
    """Heat maps on disk: per policy its share of laps flown alone, and the ego's win share, over
    latency (columns) x profile and noise (rows)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    g = result["grid"]
    lats = list(g["latencies_ms"])
    rows = [(p, n) for p in g["profiles"] for n in g["noise_mm"]]
    panels = [(f"{pol} alone: laps flown", lambda c, pol=pol: (c["alone"].get(pol) or {}).get("lap_share"))
              for pol in (g["ego"], g["opp"]) if g["alone"]]
    if g["duels"]:
        panels.append((f"{g['ego']} vs {g['opp']}: {g['ego']} wins",
                       lambda c: (c.get("duel") or {}).get("ego_win_share")))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 0.6 * len(rows) + 1.8), squeeze=False)
    by = {(c["latency_ms"], c["profile"], c["noise_mm"]): c for c in result["cells"]}
    for ax, (title, value) in zip(axes[0], panels):
        m = np.full((len(rows), len(lats)), np.nan)
        for i, (p, n) in enumerate(rows):
            for j, lat in enumerate(lats):
                v = value(by[(lat, p, n)])
                if v is not None:
                    m[i, j] = v
        ax.imshow(m, vmin=0.0, vmax=1.0, cmap="RdYlGn", aspect="auto")
        for i in range(len(rows)):
            for j in range(len(lats)):
                if not np.isnan(m[i, j]):
                    ax.text(j, i, f"{m[i, j]:.0%}", ha="center", va="center", fontsize=9)
        ax.set_xticks(range(len(lats)), [f"{v:g}" for v in lats])
        ax.set_yticks(range(len(rows)), [f"{p}, {n:g} mm" for p, n in rows])
        ax.set_xlabel("mocap latency (ms)")
        ax.set_title(title, fontsize=10)
    fig.suptitle(f"{g['track']}: lockstep flight stack, {len(g['seeds'])} seeds per cell", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write(result: dict, out: Path) -> dict[str, Path]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {"json": out / "robustness.json", "md": out / "robustness.md", "png": out / "robustness.png"}
    files["json"].write_text(json.dumps(result, indent=1, default=str) + "\n")
    files["md"].write_text(markdown_table(result))
    heatmap(result, files["png"])
    return files
