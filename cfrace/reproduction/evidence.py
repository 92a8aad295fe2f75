"""`cfrace reproduce`: the paper's evidence, measured on the shipped policies, in one report.

For each of the four settings (lemniscate / complex, without / with obstacles) and the shipped
policies of the four schemes (ds, ss, dm, ours; a scheme without a shipped policy is reported as
missing): Table I (the single-agent benchmark), the head-to-head matrix with its heatmap, ours
against DS on fresh seeds; then the competition-behaviour figure (ours in self-play on the complex
track: speed against a live opponent and after it crashed), the training curves committed beside
the policies (policies/curves/), and each claim of the paper next to the measured figure with
whether its trend holds here. Everything goes to OUT/report.md, OUT/report.json and PNGs in OUT.
"""

from __future__ import annotations

import json
import re
import subprocess
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from cfrace.errors import ConfigError, PolicyError
from cfrace.reproduction import paper
from cfrace.reproduction.paper import SCHEMES, SETTINGS, setting_name
from cfrace.reproduction.report import claims, markdown
from cfrace.paths import POLICIES_DIR

CURVES_DIR = POLICIES_DIR / "curves"


@dataclass(frozen=True)
class ReproduceConfig:
    out: Path
    quick: bool = False                    #: a few runs per cell (CI size)
    seed: int = 0                          #: seed of Table I and the matrices
    test_seeds: tuple[int, ...] = (1, 2, 3)  #: fresh seeds of the ours-vs-DS races
    runs: int = 50                         #: Table I runs per policy
    races: int = 50                        #: races per pair
    laps: int = 3
    settings: tuple = SETTINGS

    @staticmethod
    def make(out: Path, quick: bool = False, **kw) -> "ReproduceConfig":
        if quick:
            kw = {"runs": 4, "races": 4, "laps": 1, "test_seeds": (1,), **kw}
        cfg = ReproduceConfig(Path(out), quick, **kw)
        if cfg.runs < 1 or cfg.races < 1 or cfg.laps < 1:
            raise ConfigError("runs, races and laps must be >= 1")
        return cfg


def slug(track: str, obstacles: bool) -> str:
    return f"{track}{'_obstacles' if obstacles else ''}"


def shipped(track: str, obstacles: bool) -> list[str]:
    """The schemes that have a shipped policy for this setting, in SCHEMES order."""
    from cfrace.policy import resolve_policy

    have = []
    for scheme in SCHEMES:
        try:
            resolve_policy(scheme, track, obstacles)
        except PolicyError:
            continue
        have.append(scheme)
    return have


# ------------------------------------------------------------------------------------ sections

def table_i(cfg: ReproduceConfig, track: str, obstacles: bool, schemes: list[str]) -> list[dict]:
    """Single-agent benchmark rows of this setting, with the paper's figures and the trend check."""
    from cfrace.evaluate.single import evaluate

    rows = []
    for scheme in SCHEMES:  # the paper's rows without a shipped policy: its figures, nothing measured
        ref = paper.TABLE_I.get((scheme, track, obstacles))
        if scheme not in schemes and ref is not None:
            rows.append({"setting": setting_name(track, obstacles), "scheme": scheme, "ttc_s": None, "speed_mps": None,
                         "collisions": None, "success": None, "trend_holds": None,
                         "paper": dict(zip(("ttc_s", "speed_mps", "collisions", "success_pct"), ref))})
    if not schemes:
        return rows
    res = evaluate(schemes, track, obstacles, cfg.runs, cfg.laps, cfg.seed)
    for r in res.rows:
        ref = paper.TABLE_I.get((r["method"], track, obstacles))
        row = {"setting": setting_name(track, obstacles), "scheme": r["method"], "ttc_s": r["lap_time_s"],
               "speed_mps": r["avg_speed_mps"], "collisions": r["collisions"], "success": r["success_rate"],
               "paper": None if ref is None else dict(zip(("ttc_s", "speed_mps", "collisions", "success_pct"), ref))}
        # the trend: succeeds (>= 50 % of runs) or fails, as in the paper
        row["trend_holds"] = None if ref is None else (r["success_rate"] >= 0.5) == (ref[3] >= 50)
        rows.append(row)
    return sorted(rows, key=lambda r: SCHEMES.index(r["scheme"]))


def matrix(cfg: ReproduceConfig, track: str, obstacles: bool, schemes: list[str]) -> dict | None:
    """Head-to-head matrix of this setting (win rate of row vs column) and its heatmap."""
    from cfrace.evaluate.race import tournament

    if len(schemes) < 2:
        return None
    png = cfg.out / f"h2h_{slug(track, obstacles)}.png"
    res = tournament(schemes, track, obstacles, cfg.races, cfg.laps, cfg.seed, heatmap=png)
    avg = dict(zip(res.policies, res.average_win_rate()))
    return {"policies": res.policies, "win_rate": res.win_rate, "draw_rate": res.draw_rate, "average_win_rate": avg,
            "heatmap": png.name}


def ours_vs_ds(cfg: ReproduceConfig, track: str, obstacles: bool, schemes: list[str]) -> dict | None:
    """ours against DS on the default seed and on fresh seeds (the races it was not chosen on)."""
    from cfrace.evaluate.race import race

    if not {"ours", "ds"} <= set(schemes):
        return None
    seeds = (cfg.seed, *[s for s in cfg.test_seeds if s != cfg.seed])
    wins = {s: race(track, "ours", "ds", obstacles, cfg.races, cfg.laps, s).rates()["ego_win_rate"] for s in seeds}
    fresh = [wins[s] for s in seeds[1:]]
    return {"by_seed": wins, "default_seed": wins[cfg.seed],
            "fresh_mean": sum(fresh) / len(fresh) if fresh else None, "fresh_seeds": list(seeds[1:])}


def competition(cfg: ReproduceConfig) -> dict | None:
    """ours in self-play on the complex track: speeds against a live and a crashed opponent."""
    from cfrace.evaluate.race import race

    if "ours" not in shipped("complex", False):
        return None
    plot_dir = cfg.out / "competition"
    res = race("complex", "ours", "ours", False, cfg.races, cfg.laps, cfg.seed, plot_dir=plot_dir)
    prof = res.speed_profile
    live, dead = prof["vs_live_opponent"], prof["vs_crashed_opponent"]
    holds = None
    if live.get("max_mps") is not None and dead.get("max_mps") is not None:
        holds = live["max_mps"] > dead["max_mps"] and live["mean_mps"] > dead["mean_mps"]
    return {"measured": prof, "paper": paper.COMPETITION, "trend_holds": holds,
            "plots": [str(p.relative_to(cfg.out)) for p in res.plots]}


TRANSFER_PROFILE = "cf21bl"      #: the flown drone in the transfer test (the shipped policies trained on cf2x_paper)
TRANSFER_NOISE_M = 0.0005        #: m, mocap noise of the transfer dry-runs
TRANSFER_LATENCY_S = 0.010       #: s, mocap latency of the transfer dry-runs (compensated as `fly` does)
RACE_END_KINDS = ("finished", "timeout", "all_stopped", "operator_kill")  #: stops that are the race's end, not a failure


def _attempted(laps: int, finished: bool) -> int:
    """Laps attempted by a drone that completed ``laps``: one more if it did not finish."""
    return laps + (0 if finished else 1)


def transfer(cfg: ReproduceConfig) -> list[dict]:
    """The paper's sim-to-real comparison, sim-to-sim: DS and ours race each other through the whole
    flight stack (lockstep dry-run: the simulated firmware and link, mocap noise and latency) on a drone
    profile they were not trained on, against the same races (ground starts) in the training simulator
    on their own profile: average-speed gap, failures (terminal crashes or safety stops) and collisions
    per attempted lap."""
    from cfrace.evaluate.race import race
    from cfrace.flight.config import FlightConfig
    from cfrace.rehearsal.dryrun import dry_run

    races = 2 if cfg.quick else 10
    out = []
    for track in ("lemniscate", "complex"):
        if not {"ours", "ds"} <= set(shipped(track, False)):
            continue
        sim = race(track, "ours", "ds", False, races, cfg.laps, cfg.seed, start="ground")
        stack = {"ours": [], "ds": []}
        for k in range(races):  # swap the slots every other race, as the simulator's races do
            ego, opp = ("ours", "ds") if k % 2 == 0 else ("ds", "ours")
            fc = FlightConfig(track=track, ego=ego, opp=opp, laps=cfg.laps, profile=TRANSFER_PROFILE, quiet=True,
                              rt_priority=0, loop_cpu="off")
            res = dry_run(fc, lockstep=True, seed=cfg.seed + k, mocap_noise_m=TRANSFER_NOISE_M,
                          mocap_latency_s=TRANSFER_LATENCY_S)
            for d, name in zip(res.drones, (ego, opp)):
                stack[name].append(d)
        for name, stats in (("ours", sim.ego_stats), ("ds", sim.opp_stats)):
            ds_ = stack[name]
            fin = [d["laps"] >= cfg.laps for d in ds_]
            failed = [not f and d["stopped"] and d["stop_kind"] not in RACE_END_KINDS for d, f in zip(ds_, fin)]
            att = sum(_attempted(d["laps"], f) for d, f in zip(ds_, fin))
            speeds = [d["speed_mean"] for d in ds_ if d["speed_mean"] is not None]
            sim_att = stats["laps_completed"] + (stats["runs"] - round(stats["finish_rate"] * stats["runs"]))
            row = {"track": track, "policy": name, "races": races, "profile_flown": TRANSFER_PROFILE,
                   "sim_speed_mps": stats["avg_speed_mps"],
                   "stack_speed_mps": sum(speeds) / len(speeds) if speeds else None,
                   "sim_failure_rate": stats["crashes"] / max(sim_att, 1),
                   "stack_failure_rate": sum(failed) / max(att, 1),
                   "sim_collision_rate": stats["collisions"] / max(sim_att, 1),
                   "stack_stops": {k: sum(1 for d, x in zip(ds_, failed) if x and d["stop_kind"] == k)
                                   for k in sorted({d["stop_kind"] for d, x in zip(ds_, failed) if x})}}
            row["speed_gap_mps"] = (None if row["stack_speed_mps"] is None or row["sim_speed_mps"] is None
                                    else row["sim_speed_mps"] - row["stack_speed_mps"])
            row["paper_speed_gap_mps"] = paper.TRANSFER_SPEED_GAP[name]
            out.append(row)
    return out


def curve_files() -> dict[tuple[str, str], list[Path]]:
    """policies/curves/{scheme}_{track}[_obstacles]_s{seed}.csv grouped by (scheme, setting slug)."""
    groups: dict[tuple[str, str], list[Path]] = {}
    for f in sorted(CURVES_DIR.glob("*.csv")):
        m = re.fullmatch(r"(ds|ss|dm|ours)_(.+)_s\d+", f.stem)
        if m:
            groups.setdefault((m.group(1), m.group(2)), []).append(f)
    return groups


def curves(cfg: ReproduceConfig) -> list[dict]:
    """One plot per setting: each scheme's mean episode return and gates/s over its runs' seeds."""
    from cfrace.rl.curves import plot_curves

    groups = curve_files()
    out = []
    for track, obstacles in cfg.settings:
        s = slug(track, obstacles)
        mine = {scheme: files for (scheme, setting), files in groups.items() if setting == s}
        if not mine:
            continue
        for y in ("stat_gates_per_s", "return_agent0"):
            png = plot_curves(mine, cfg.out / f"curves_{s}_{y}.png", y,
                              f"{setting_name(track, obstacles)}: training curves (mean, min-max over seeds)")
            if png is not None:
                out.append({"setting": setting_name(track, obstacles), "y": y, "png": png.name,
                            "runs": {k: [f.name for f in v] for k, v in mine.items()}})
    return out


# ------------------------------------------------------------------------------------ report

def robustness(cfg: ReproduceConfig) -> dict | None:
    """The shipped lemniscate ours and DS over the robustness grid (cfrace.evaluate.robustness,
    `cfrace sim robustness`) on the fresh seeds, its CI size with --quick; table and heat map in
    OUT/robustness/. None when either policy is not shipped."""
    from cfrace.evaluate.robustness import Grid, run_grid, write
    if not {"ours", "ds"} <= set(shipped("lemniscate", False)):
        return None
    grid = Grid(seeds=cfg.test_seeds)
    result = run_grid(grid.quick() if cfg.quick else grid)
    files = write(result, cfg.out / "robustness")
    return {"grid": result["grid"], "cells": result["cells"], "wall_s": result["wall_s"],
            "png": str(files["png"].relative_to(cfg.out))}


def _commit() -> str:
    try:
        return subprocess.run(["git", "-C", str(POLICIES_DIR.parent), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, timeout=5).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def reproduce(cfg: ReproduceConfig, on_progress=None) -> dict:
    """Run every section, write OUT/report.md and OUT/report.json; the report as a dict."""
    t0 = time.perf_counter()
    cfg.out.mkdir(parents=True, exist_ok=True)
    say = on_progress or (lambda text: None)
    report: dict = {"config": {**asdict(cfg), "out": str(cfg.out)}, "commit": _commit(),
                    "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                    "table_i": [], "settings": {}, "missing": {}}
    for track, obstacles in cfg.settings:
        name = setting_name(track, obstacles)
        schemes = shipped(track, obstacles)
        report["missing"][name] = [s for s in SCHEMES if s not in schemes]
        say(f"{name}: Table I ({', '.join(schemes) or 'no policies'})")
        report["table_i"] += table_i(cfg, track, obstacles, schemes)
        say(f"{name}: head-to-head matrix")
        sec = {"schemes": schemes, "matrix": matrix(cfg, track, obstacles, schemes)}
        say(f"{name}: ours vs DS on fresh seeds")
        sec["ours_vs_ds"] = ours_vs_ds(cfg, track, obstacles, schemes)
        report["settings"][name] = sec
    say("competition behaviour (complex, self-play)")
    report["competition"] = competition(cfg)
    say("transfer through the flight stack (lockstep dry-runs on another drone profile)")
    report["transfer"] = transfer(cfg)
    report["transfer_setup"] = {"profile": TRANSFER_PROFILE, "noise_m": TRANSFER_NOISE_M, "latency_s": TRANSFER_LATENCY_S}
    say("robustness: latency x drone profile x mocap noise through the flight stack")
    report["robustness"] = robustness(cfg)
    say("training curves")
    report["curves"] = curves(cfg)
    report["claims"] = claims(report)
    report["wall_s"] = round(time.perf_counter() - t0, 1)
    (cfg.out / "report.json").write_text(json.dumps(report, indent=2, default=str) + "\n")
    (cfg.out / "report.md").write_text(markdown(report))
    return report
