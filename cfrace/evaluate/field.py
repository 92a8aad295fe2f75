"""Races of N drones (`cfrace race --entrants A,B,C,D`) and free-for-all tournaments with a rating
(`cfrace tournament P... --field N`), all races batched in one simulator.

Each race starts from the track's start grid (cfrace.track.start_grid) before a random gate (or
on the floor before gate 0), each drone in a random slot; entrant k flies drone k. A race runs
until every drone has finished or crashed (or the time limit): the finishing order is complete.
Places, winners and the rating: cfrace.evaluate.rating. A policy trained for two drones sees one
opponent, picked by the race's opponent rule (cfrace.contract.observations.choose_opponents) unless
its metadata names its own.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path

import numpy as np

from cfrace.contract.observations import DEFAULT_OPPONENT_RULE, OPPONENT_RULES
from cfrace.errors import ConfigError
from cfrace.evaluate.entrants import common_profile, load_entrants, load_race_track
from cfrace.evaluate.metrics import solo_metrics
from cfrace.evaluate.plots import field_plots, plot_ratings
from cfrace.evaluate.rating import fit_ratings, pairwise, placings, winners
from cfrace.evaluate.rollout import LAP_TIME_LIMIT_S, RacesRun, Recording, Starts, rollout, start_poses
from cfrace.sim.simulator import REASONS

PLOT_RACES = 4            #: races whose positions are recorded for the plots
MAX_FIELD = 16            #: drones per race (the C kernel's limit per world)


def _check(n: int, races: int, laps: int, rule: str) -> None:
    if n < 2 or n > MAX_FIELD:
        raise ConfigError(f"a race needs 2 to {MAX_FIELD} entrants, got {n}")
    if races < 1 or laps < 1:
        raise ConfigError("races and laps must be >= 1")
    if rule not in OPPONENT_RULES:
        raise ConfigError(f"--opponent-rule {rule!r}: one of {', '.join(OPPONENT_RULES)}")


def _policy_key(path: Path) -> str:
    return str(Path(path).resolve())


@dataclass
class FieldResult(RacesRun):
    opponent_rule: str
    entrants: list[str]             #: display names, drone k = entrant k
    policies: list[str]             #: the policy each entrant flies (repeats share one)
    places: np.ndarray              #: (R, N) int, 1 = first
    winner: np.ndarray              #: (R,) drone index, -1 = nobody won
    finish_time: np.ndarray         #: (R, N) s, nan = did not finish
    crashed: np.ndarray             #: (R, N) bool
    crash_reason: np.ndarray        #: (R, N) int (cfrace.sim.simulator.REASONS)
    crash_partner: np.ndarray       #: (R, N) int, the drone touched at the crash step (-1: none)
    pair_contacts: np.ndarray       #: (N, N) int, new drone-drone contacts of each pair, all races
    stats: list[dict]               #: per entrant: lap time, speed, crashes... (metrics.solo_metrics)
    recording: Recording | None = None
    plots: list[Path] = field(default_factory=list)
    wall_s: float = 0.0

    def win_rates(self) -> list[float]:
        return [float((self.winner == k).mean()) for k in range(len(self.entrants))]

    def policy_win_rates(self) -> dict[str, float]:
        """Share of races won by any entrant flying that policy (e.g. "an ours policy first")."""
        out = {}
        for p in dict.fromkeys(self.policies):
            ks = [k for k, q in enumerate(self.policies) if q == p]
            out[p] = float(np.isin(self.winner, ks).mean())
        return out

    def crash_causes(self) -> list[dict[str, int]]:
        """Per entrant: crashes by reason, and "drone_contact" for crashes while touching another."""
        out = []
        for k in range(len(self.entrants)):
            c = self.crashed[:, k]
            causes = {REASONS[int(v)]: int((self.crash_reason[c, k] == v).sum()) for v in np.unique(self.crash_reason[c, k])}
            causes["while_touching_a_drone"] = int((self.crash_partner[c, k] >= 0).sum())
            out.append(causes)
        return out

    def contacts_by_pair(self) -> list[dict]:
        n = len(self.entrants)
        rows = []
        for i, j in combinations(range(n), 2):
            crashes = int(((self.crash_partner[:, i] == j) & self.crashed[:, i]).sum()
                          + ((self.crash_partner[:, j] == i) & self.crashed[:, j]).sum())
            rows.append({"pair": [self.entrants[i], self.entrants[j]], "contacts": int(self.pair_contacts[i, j]),
                         "crashes_in_contact": crashes})
        return rows

    def to_json(self) -> dict:
        n = len(self.entrants)
        order = [[self.entrants[k] for k in np.argsort(p, kind="stable")] for p in self.places]
        return {"track": self.track, "obstacles": self.obstacles, "races": self.races, "laps": self.laps,
                "seed": self.seed, "time_limit_s": self.time_limit_s, "opponent_rule": self.opponent_rule,
                "entrants": self.entrants, "policies": self.policies,
                "win_rate": dict(zip(self.entrants, self.win_rates())),
                "policy_win_rate": self.policy_win_rates(),
                "no_winner_rate": float((self.winner < 0).mean()),
                "mean_place": {self.entrants[k]: float(self.places[:, k].mean()) for k in range(n)},
                "place_counts": {self.entrants[k]: [int((self.places[:, k] == p).sum()) for p in range(1, n + 1)]
                                 for k in range(n)},
                "crash_causes": dict(zip(self.entrants, self.crash_causes())),
                "contacts_by_pair": self.contacts_by_pair(),
                "stats": dict(zip(self.entrants, self.stats)),
                "finishing_order": order, "wall_s": round(self.wall_s, 3)}


def _rollout_field(track, prof, obstacles, entrants, assign, starts, laps, limit, record, seed, threads, rule):
    rec = rollout(track, prof, obstacles, entrants, assign, starts, laps, limit, record, seed, threads,
                  until_all=True, opponent_rule=rule)
    s = rec.summary()
    return rec, s, placings(s.finish_time, rec.gates_passed)


def race_field(track_name: str, entrants: list[str], obstacles: bool = False, races: int = 50, laps: int = 3,
               seed: int = 0, time_limit_s: float | None = None, profile: str | None = None,
               plot_dir: Path | None = None, threads: int | None = None, start: str = "gate",
               opponent_rule: str = DEFAULT_OPPONENT_RULE) -> FieldResult:
    """``races`` races of all ``entrants`` at once (drone k = entrant k; repeats allowed)."""
    t0 = time.perf_counter()
    n = len(entrants)
    _check(n, races, laps, opponent_rule)
    track = load_race_track(track_name, obstacles)
    ents = load_entrants(entrants, track, obstacles)
    prof = common_profile(ents, profile)
    starts = start_poses(track, prof, races, n, obstacles, seed, start=start)
    assign = np.tile(np.arange(n), (races, 1))
    record = tuple(range(min(races, PLOT_RACES))) if plot_dir is not None else ()
    limit = laps * LAP_TIME_LIMIT_S if time_limit_s is None else time_limit_s
    rec, s, places = _rollout_field(track, prof, obstacles, ents, assign, starts, laps, limit, record, seed, threads,
                                    opponent_rule)
    result = FieldResult(track.name, obstacles, races, laps, seed, limit, opponent_rule, [e.name for e in ents],
                         [e.path.stem for e in ents], places, winners(s.finish_time, places), s.finish_time,
                         s.crashed, s.crash_reason, rec.crash_partner, np.triu(rec.pair_contacts.sum(0), 1),
                         [solo_metrics(s, slice(None), k) for k in range(n)], recording=rec)
    if plot_dir is not None:
        result.plots = field_plots(plot_dir, track, obstacles, result.entrants, rec, places)
    result.wall_s = time.perf_counter() - t0
    return result


@dataclass
class FreeForAllResult:
    track: str
    obstacles: bool
    field_size: int
    races: int                      #: per heat
    laps: int
    seed: int
    opponent_rule: str
    policies: list[str]
    heats: list[list[str]]
    rating: list[float]             #: Elo scale (cfrace.evaluate.rating)
    wins: list[int]                 #: races won
    starts: list[int]               #: races entered
    mean_place: list[float]
    pair_win_rate: list[list[float | None]]   #: [i][j] share of meetings where i placed ahead (ties half)
    plots: list[Path] = field(default_factory=list)
    wall_s: float = 0.0

    def to_json(self) -> dict:
        return {"track": self.track, "obstacles": self.obstacles, "field_size": self.field_size,
                "races_per_heat": self.races, "laps": self.laps, "seed": self.seed,
                "opponent_rule": self.opponent_rule, "policies": self.policies, "heats": self.heats,
                "rating": dict(zip(self.policies, [round(r, 1) for r in self.rating])),
                "wins": dict(zip(self.policies, self.wins)), "races_entered": dict(zip(self.policies, self.starts)),
                "mean_place": dict(zip(self.policies, self.mean_place)), "pair_win_rate": self.pair_win_rate,
                "wall_s": round(self.wall_s, 3)}


def free_for_all(policies: list[str], track_name: str, field_size: int = 4, obstacles: bool = False,
                 races: int = 20, laps: int = 3, seed: int = 0, time_limit_s: float | None = None,
                 profile: str | None = None, plot: Path | None = None, threads: int | None = None,
                 opponent_rule: str = DEFAULT_OPPONENT_RULE) -> FreeForAllResult:
    """Every ``field_size``-subset of ``policies`` (a heat) races ``races`` times from the same starts,
    all heats in one batched rollout; ratings from every race's placings."""
    t0 = time.perf_counter()
    p = len(policies)
    if p < field_size:
        raise ConfigError(f"a free-for-all of fields of {field_size} needs at least {field_size} policies, got {p}")
    _check(field_size, races, laps, opponent_rule)
    track = load_race_track(track_name, obstacles)
    ents = load_entrants(policies, track, obstacles)
    prof = common_profile(ents, profile)
    heats = list(combinations(range(p), field_size))
    starts = start_poses(track, prof, races, field_size, obstacles, seed)
    assign = np.array([h for h in heats for _ in range(races)], dtype=np.int64)
    h = len(heats)
    all_starts = Starts(*(x.repeat(h, *([1] * (x.dim() - 1))) for x in (starts.pos, starts.quat, starts.target)))
    limit = laps * LAP_TIME_LIMIT_S if time_limit_s is None else time_limit_s
    rec, s, places = _rollout_field(track, prof, obstacles, ents, assign, all_starts, laps, limit, (), seed, threads,
                                    opponent_rule)
    wins_pair, games = pairwise(places, assign, p)
    rating = fit_ratings(wins_pair, games)
    win = winners(s.finish_time, places)
    won = np.where(win >= 0, assign[np.arange(len(win)), np.maximum(win, 0)], -1)
    entered = [int((assign == i).sum()) for i in range(p)]
    mean_place = [float(places[assign == i].mean()) for i in range(p)]
    with np.errstate(invalid="ignore", divide="ignore"):
        pw = np.where(games > 0, wins_pair / games, np.nan)
    pair_rate = [[None if np.isnan(v) else float(v) for v in row] for row in pw]
    result = FreeForAllResult(track.name, obstacles, field_size, races, laps, seed, opponent_rule,
                              [e.name for e in ents], [[ents[i].name for i in hh] for hh in heats],
                              [float(r) for r in rating], [int((won == i).sum()) for i in range(p)], entered,
                              mean_place, pair_rate)
    if plot is not None:
        title = (f"{track.name}: free-for-all, fields of {field_size}, {races} races per heat x {len(heats)} heats")
        result.plots = [plot_ratings(plot, result.policies, result.rating, result.mean_place, title)]
    result.wall_s = time.perf_counter() - t0
    return result
