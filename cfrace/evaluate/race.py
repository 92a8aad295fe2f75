"""Head-to-head races and tournaments, all races of all pairs batched in one simulator.

Race rules (paper Sec. IV-A, docs/evaluation.md): the first drone to complete the laps wins (also
when the other crashed before); a terminal crash of both is a draw; a time-out with nobody finished
is a draw too (counted apart). Races come in pairs from one start configuration with the two slots
swapped, so half of the races swap the starting slots. Drone 0 is always the ego, drone 1 the
opponent; each is fed the observation layout its own metadata names.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from cfrace.errors import ConfigError
from cfrace.evaluate.entrants import Entrant, common_profile, load_entrants, load_race_track
from cfrace.evaluate.metrics import RunSummary, finish_speed, race_outcomes, race_rates, solo_metrics, speed_stats
from cfrace.evaluate.plots import plot_heatmap, race_plots
from cfrace.evaluate.rollout import LAP_TIME_LIMIT_S, RacesRun, Recording, Starts, rollout, start_poses
from cfrace.sim.simulator import REASONS

PLOT_RACES = 4        #: races whose positions are recorded for the plots
CRASHED_OPP_RACES = 10  #: extra worlds (with --plot) where the opponent drops at the start


@dataclass
class RaceResult(RacesRun):
    ego: str
    opp: str
    outcomes: np.ndarray                   # (races,) outcome codes (metrics.OUTCOMES)
    swapped: np.ndarray                    # (races,) bool, the slots were swapped
    ego_stats: dict
    opp_stats: dict
    speed_profile: dict | None = None      # Fig. 8 figures (with --plot)
    recording: Recording | None = None
    plots: list[Path] = field(default_factory=list)
    wall_s: float = 0.0

    def rates(self) -> dict:
        return race_rates(self.outcomes)

    def to_json(self) -> dict:
        r = self.rates()
        sw = self.swapped
        out = {"track": self.track, "obstacles": self.obstacles, "races": self.races, "laps": self.laps,
               "seed": self.seed, "time_limit_s": self.time_limit_s, "ego_policy": self.ego, "opp_policy": self.opp,
               "ego_win_rate": r["ego_win_rate"], "opp_win_rate": r["opp_win_rate"], "draw_rate": r["draw_rate"],
               "counts": r["counts"], "swapped_races": int(sw.sum()),
               "ego_win_rate_by_slot": {"own_slot": race_rates(self.outcomes[~sw])["ego_win_rate"] if (~sw).any() else None,
                                        "swapped": race_rates(self.outcomes[sw])["ego_win_rate"] if sw.any() else None},
               "ego_stats": self.ego_stats, "opp_stats": self.opp_stats, "wall_s": round(self.wall_s, 3)}
        if self.speed_profile is not None:
            out["speed_profile"] = self.speed_profile
        return out


def _pair_worlds(pairs: list[tuple[int, int]], races: int, starts: Starts) -> tuple[np.ndarray, Starts]:
    """Worlds for every pair (ego index, opp index) x ``races``; every pair uses the same starts."""
    assign = np.array([[i, j] for i, j in pairs for _ in range(races)], dtype=np.int64).reshape(-1, 2)
    n = len(pairs)
    rep = lambda x: x.repeat(n, *([1] * (x.dim() - 1)))
    return assign, Starts(rep(starts.pos), rep(starts.quat), rep(starts.target))


def _drone_stats(summary: RunSummary, worlds: slice, drone: int) -> dict:
    m = solo_metrics(summary, worlds, drone)
    m["finish_rate"] = m.pop("success_rate")
    return m


def race(track_name: str, ego: str, opp: str, obstacles: bool = False, races: int = 50, laps: int = 3,
         seed: int = 0, time_limit_s: float | None = None, profile: str | None = None,
         plot_dir: Path | None = None, threads: int | None = None, start: str = "gate",
         record_all: bool = False) -> RaceResult:
    """``races`` head-to-head races of ``ego`` (drone 0) against ``opp`` (drone 1); ``start`` as in
    start_poses ("gate": in the air before a random gate; "ground": side by side on the floor).
    ``record_all``: the recording keeps positions of every race (else only of the plotted ones)."""
    t0 = time.perf_counter()
    if races < 1 or laps < 1:
        raise ConfigError("races and laps must be >= 1")
    track = load_race_track(track_name, obstacles)
    entrants = load_entrants([ego, opp], track, obstacles)
    prof = common_profile(entrants, profile)
    starts = start_poses(track, prof, races, 2, obstacles, seed, swap_pairs=True, start=start)
    assign, all_starts = _pair_worlds([(0, 1)], races, starts)
    extra = min(races, CRASHED_OPP_RACES) if plot_dir is not None else 0
    if extra:  # the same ego from the same starts, the opponent drops at once (motors off)
        assign = np.concatenate([assign, np.tile([[0, -1]], (extra, 1))])
        all_starts = Starts(*(torch.cat([a, a[:extra]]) for a in (all_starts.pos, all_starts.quat, all_starts.target)))
    record = (tuple(range(min(races, PLOT_RACES))) + tuple(range(races, races + min(extra, PLOT_RACES)))
              if plot_dir is not None else tuple(range(races)) if record_all else ())
    limit = laps * LAP_TIME_LIMIT_S if time_limit_s is None else time_limit_s
    rec = rollout(track, prof, obstacles, entrants, assign, all_starts, laps, limit, record, seed, threads)
    s = rec.summary()
    live = slice(0, races)
    outcomes = race_outcomes(s.finish_time[live], s.crashed[live])
    swapped = np.arange(races) % 2 == 1
    result = RaceResult(track.name, obstacles, races, laps, seed, limit, entrants[0].name, entrants[1].name,
                        outcomes, swapped, _drone_stats(s, live, 0), _drone_stats(s, live, 1), recording=rec)
    if plot_dir is not None:
        result.speed_profile = speed_profile(rec, s, races)
        result.plots = race_plots(plot_dir, track, obstacles, entrants, rec, s, races, result.speed_profile)
    result.wall_s = time.perf_counter() - t0
    return result


def speed_profile(rec: Recording, s: RunSummary, races: int) -> dict:
    """Fig. 8 figures of the ego (drone 0), whole races from the same starts: against a live
    opponent (the race worlds in which the opponent never crashed) vs against a crashed one (the
    extra worlds, where the opponent drops at the start). Max / mean speed m/s over the ego's
    racing steps, mean speed at the finish (the paper's final-gate speed)."""
    act, sp = rec.active[..., 0] & ~rec.crashed_now[..., 0], rec.speed[..., 0]   # the crash step reads 0
    fin = finish_speed(rec.speed, rec.lap_stamp, rec.active, s.finished)[:, 0]
    live = np.zeros(act.shape[1], bool)
    live[:races] = ~s.crashed[:races, 1]
    extra = np.zeros(act.shape[1], bool)
    extra[races:] = True
    mean = lambda x: float(np.nanmean(x)) if (~np.isnan(x)).any() else None
    return {
        "vs_live_opponent": {**speed_stats(sp[:, live], act[:, live]), "races": int(live.sum()),
                             "finish_speed_mps": mean(fin[live])},
        "vs_crashed_opponent": {**speed_stats(sp[:, extra], act[:, extra]), "races": int(extra.sum()),
                                "finish_speed_mps": mean(fin[extra])},
    }


@dataclass
class TournamentResult:
    track: str
    obstacles: bool
    races: int
    laps: int
    seed: int
    policies: list[str]
    win_rate: list[list[float | None]]     # [row][col]: row's win rate against col (None on the diagonal)
    draw_rate: list[list[float | None]]
    pairs: list[dict]
    plots: list[Path] = field(default_factory=list)
    wall_s: float = 0.0

    def to_json(self) -> dict:
        return {"track": self.track, "obstacles": self.obstacles, "races": self.races, "laps": self.laps,
                "seed": self.seed, "policies": self.policies, "win_rate": self.win_rate, "draw_rate": self.draw_rate,
                "average_win_rate": self.average_win_rate(), "pairs": self.pairs, "wall_s": round(self.wall_s, 3)}

    def average_win_rate(self) -> list[float | None]:
        out = []
        for row in self.win_rate:
            v = [x for x in row if x is not None]
            out.append(sum(v) / len(v) if v else None)
        return out


def tournament_pairs(policies: list[str], track_name: str, obstacles: bool, races: int, laps: int, seed: int,
                     time_limit_s: float | None, profile: str | None, threads: int | None,
                     pairs: list[tuple[int, int]]) -> list[dict]:
    """Race the given pairs of ``policies`` (indices; all pairs in one batched rollout) from the
    tournament's starts; one row per pair: win/draw rates and lap times. A world's race does not
    depend on the other worlds of the batch, so any split of the pairs gives the same rows."""
    track = load_race_track(track_name, obstacles)
    entrants = load_entrants(policies, track, obstacles)
    prof = common_profile(entrants, profile)
    starts = start_poses(track, prof, races, 2, obstacles, seed, swap_pairs=True)
    assign, all_starts = _pair_worlds(pairs, races, starts)
    limit = laps * LAP_TIME_LIMIT_S if time_limit_s is None else time_limit_s
    rec = rollout(track, prof, obstacles, entrants, assign, all_starts, laps, limit, (), seed, threads)
    s = rec.summary()
    rows = []
    for k, (i, j) in enumerate(pairs):
        ws = slice(k * races, (k + 1) * races)
        r = race_rates(race_outcomes(s.finish_time[ws], s.crashed[ws]))
        rows.append({"ego": entrants[i].name, "opp": entrants[j].name, **r,
                     "ego_lap_time_s": solo_metrics(s, ws, 0)["lap_time_s"],
                     "opp_lap_time_s": solo_metrics(s, ws, 1)["lap_time_s"]})
    return rows


def tournament(policies: list[str], track_name: str, obstacles: bool = False, races: int = 50, laps: int = 3,
               seed: int = 0, time_limit_s: float | None = None, profile: str | None = None,
               heatmap: Path | None = None, threads: int | None = None,
               pair_runner: Callable | None = None) -> TournamentResult:
    """Every pair of policies races ``races`` times (half with swapped slots), all pairs at once.
    Cell [i][j] is i's win rate against j; the ordered pair (j, i) is the same races seen from j.
    ``pair_runner`` (same arguments and result as tournament_pairs) races the pairs elsewhere, e.g.
    spread over Ray workers (cfrace.evaluate.ray_tournament)."""
    t0 = time.perf_counter()
    if len(policies) < 2:
        raise ConfigError("a tournament needs at least 2 policies")
    if races < 1 or laps < 1:
        raise ConfigError("races and laps must be >= 1")
    track = load_race_track(track_name, obstacles)
    entrants = load_entrants(policies, track, obstacles)
    common_profile(entrants, profile)
    pairs = list(combinations(range(len(entrants)), 2))
    limit = laps * LAP_TIME_LIMIT_S if time_limit_s is None else time_limit_s
    paths = [str(e.path) for e in entrants]
    pair_rows = (pair_runner or tournament_pairs)(paths, track_name, obstacles, races, laps, seed, limit, profile,
                                                  threads, pairs)
    n = len(entrants)
    win = [[None] * n for _ in range(n)]
    draw = [[None] * n for _ in range(n)]
    for (i, j), row in zip(pairs, pair_rows):
        row["ego"], row["opp"] = entrants[i].name, entrants[j].name   # display names (#2 for repeats)
        win[i][j], win[j][i] = row["ego_win_rate"], row["opp_win_rate"]
        draw[i][j] = draw[j][i] = row["draw_rate"]
    result = TournamentResult(track.name, obstacles, races, laps, seed, [e.name for e in entrants], win, draw,
                              pair_rows)
    if heatmap is not None:
        title = (f"{track.name}{' with obstacles' if obstacles else ''}: win rate of row vs column "
                 f"({races} races x {laps} laps)")
        result.plots = [plot_heatmap(heatmap, result.policies, win, draw, title)]
    result.wall_s = time.perf_counter() - t0
    return result


def race_crashes(ego: str, opp: str, track_name: str, obstacles: bool, races: int, seed: int) -> list[dict]:
    """Every race of `race(track_name, ego, opp, ...)` (3 laps) EGO crashes in: the race, the time, the crash
    reason (cfrace.sim.simulator.REASONS), the distance to the opponent, EGO's lead along the race line,
    whether the opponent was racing and EGO's track position at that step."""
    rec = race(track_name, ego, opp, obstacles, races, 3, seed, threads=1, record_all=True).recording
    out = []
    for w in range(races):
        steps = np.nonzero(rec.crashed_now[:, w, 0] & rec.active[:, w, 0])[0]
        if len(steps):
            k = steps[0]
            out.append({"race": w, "t_s": float(rec.t[k]), "reason": REASONS[int(rec.reason[k, w, 0])],
                        "opp_dist_m": float(np.linalg.norm(rec.pos[k, w, 0] - rec.pos[k, w, 1])),
                        "lead_m": float(rec.track_pos[k, w, 0] - rec.track_pos[k, w, 1]),
                        "opp_racing": bool(rec.active[k, w, 1]), "track_pos_m": float(rec.track_pos[k, w, 0])})
    return out
