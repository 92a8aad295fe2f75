"""Score a run's kept checkpoints (``cfrace train --keep-checkpoints``) and choose one.

Every ``RUN/checkpoints/itNNNNN.pt`` is exported to ONNX next to it (the parity check included) and
flown: alone (the single-agent benchmark: success, TTC) or, with an opponent, in head-to-head
races (win rate). The scores go to ``RUN/checkpoints/scores.csv``; the rule picks one:

- alone: the highest success rate, then the lowest average time to complete a lap;
- against an opponent: the highest win rate; ties go to the earliest checkpoint. With ``alone_min``
  each checkpoint is also flown alone, and the highest win rate is taken among the checkpoints that
  finish at least that share of the runs alone (all of them if none does). The opponent may be a field, a comma list with ``*`` for the
  checkpoint (``*,*,ds,ds``): N-drone races (cfrace.evaluate.field), the win rate is the share of
  races a ``*`` drone won.

Choose on validation seeds and report on others: the seed given here is the validation seed, and
`cfrace eval` / `cfrace race` with other seeds give the figures that are reported.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cfrace.errors import ConfigError

FIELDS = ("iteration", "env_steps", "wall_min", "onnx", "success", "lap_time_s", "avg_speed_mps", "collisions",
          "win_rate", "loss_rate")


@dataclass(frozen=True)
class Scored:
    rows: list[dict]        #: one per checkpoint, FIELDS
    chosen: dict            #: the row the rule picks
    csv: Path


def kept_checkpoints(run: Path) -> list[Path]:
    """RUN/checkpoints/it*.pt in iteration order."""
    folder = Path(run) / "checkpoints"
    found = sorted(folder.glob("it*.pt"), key=lambda p: int(re.sub(r"\D", "", p.stem) or 0))
    if not found:
        raise ConfigError(f"{run}: no kept checkpoints (train with --keep-checkpoints)")
    return found


def score_checkpoint(ckpt: Path, track: str, obstacles: bool, opp: str | None, runs: int, laps: int, seed: int,
                     agent: str = "best", alone: bool = False) -> dict:
    """Export one checkpoint (cached next to it) and fly it; one row of FIELDS. With an opponent and
    ``alone``, it is flown alone as well (success, lap time and speed next to the win rate)."""
    from cfrace.evaluate.race import race
    from cfrace.evaluate.single import evaluate
    from cfrace.export import export_checkpoint
    from cfrace.rl.train import load_checkpoint

    onnx = ckpt.with_suffix(f".{agent}.onnx")
    _, meta, _ = export_checkpoint(ckpt, onnx, agent)
    row = {"iteration": int(re.sub(r"\D", "", ckpt.stem) or 0), "checkpoint": str(ckpt),
           "env_steps": int(meta.get("train_steps", 0)),
           "wall_min": round(float(load_checkpoint(ckpt).get("wall_s", 0.0)) / 60.0, 2), "onnx": str(onnx)}
    if opp is None or alone:
        r = evaluate([str(onnx)], track, obstacles, runs, laps, seed).rows[0]
        row.update(success=r["success_rate"], lap_time_s=r["lap_time_s"], avg_speed_mps=r["avg_speed_mps"],
                   collisions=r["collisions"], laps_per_run=r["laps_completed"] / max(r["runs"], 1))
    if opp is not None and "," in opp:
        from cfrace.evaluate.field import race_field

        lineup = [str(onnx) if x.strip() == "*" else x.strip() for x in opp.split(",")]
        if str(onnx) not in lineup:
            raise ConfigError(f"against {opp!r}: a field needs * (the checkpoint) in it")
        r = race_field(track, lineup, obstacles, runs, laps, seed)
        mine = [k for k, x in enumerate(lineup) if x == str(onnx)]
        won = float(np.isin(r.winner, mine).mean())
        row.update(win_rate=won, loss_rate=float((r.winner >= 0).mean()) - won)
    elif opp is not None:
        rates = race(track, str(onnx), opp, obstacles, runs, laps, seed).rates()
        row.update(win_rate=rates["ego_win_rate"], loss_rate=rates["opp_win_rate"])
    return row


def choose(rows: list[dict], alone_min: float | None = None) -> dict:
    """The selection rule of the module docstring."""
    able = [r for r in rows if alone_min is not None and (r.get("success") or 0.0) >= alone_min]

    def key(r: dict):
        if r.get("win_rate") is not None:
            return (bool(able) and r not in able, -r["win_rate"], r["iteration"])
        ttc = r.get("lap_time_s")
        return (-(r.get("success") or 0.0), ttc if ttc is not None else float("inf"), r["iteration"])
    return min(rows, key=key)


def score_run(run: Path, track: str, obstacles: bool = False, opp: str | None = None, runs: int = 50,
              laps: int = 3, seed: int = 0, agent: str = "best", on_row=None, max_points: int | None = None,
              min_iteration: int = 0, alone_min: float | None = None) -> Scored:
    """Score every kept checkpoint of ``run`` (see the module docstring) and choose one; with
    ``max_points`` only that many, evenly spaced, the last one included; ``min_iteration``: only
    checkpoints from that iteration on (e.g. after a critic warm-up, whose actors are the source's);
    ``alone_min`` (with ``opp``): fly each alone too and choose among those that succeed that often."""
    ckpts = [c for c in kept_checkpoints(Path(run)) if int(re.sub(r"\D", "", c.stem) or 0) >= min_iteration]
    if not ckpts:
        raise ConfigError(f"{run}: no kept checkpoint from iteration {min_iteration} on")
    if max_points is not None and len(ckpts) > max_points:
        ckpts = [ckpts[i] for i in np.unique(np.linspace(0, len(ckpts) - 1, max_points).round().astype(int))]
    rows = []
    for ckpt in ckpts:
        rows.append(score_checkpoint(ckpt, track, obstacles, opp, runs, laps, seed, agent,
                                     alone=opp is not None and alone_min is not None))
        if on_row is not None:
            on_row(rows[-1])
    out = Path(run) / "checkpoints" / "scores.csv"
    with out.open("w", newline="") as fh:
        w = csv.DictWriter(fh, FIELDS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    return Scored(rows, choose(rows, alone_min), out)
