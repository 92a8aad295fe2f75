"""Placings of N-drone races and an Elo-scale rating fitted to them.

Placing rule (one definition, used by `cfrace race --entrants` and the free-for-all tournament):
drones that completed the laps come first, by finish time (2 ms resolution; equal times share a
place); then every other drone (crashed or timed out) by gates passed, more first; equal gates
share a place. Place 1 is first; a shared place is the best of the places it spans (1, 2, 2, 4).
The winner of a race is the drone alone in place 1 that finished; nobody finished: no winner.

Rating: every race is split into its N (N - 1) / 2 pairwise results (ahead = a win, a shared
place = half a win each); the ratings are the maximum-likelihood Bradley-Terry strengths of all
pairwise results, P(i ahead of j) = 1 / (1 + 10^((R_j - R_i) / 400)), the model Elo ratings
estimate, fitted with Hunter's MM iteration. Unlike sequential Elo updates the result does not
depend on the order of the races. A prior of ``prior_games`` drawn games of every player against
a fixed reference player rated BASE keeps ratings finite when someone wins every race (and pins
the scale). No library: the PyPI lists of this project's machines carry none of trueskill /
openskill, and this fit is 20 lines (tests/test_field.py checks it recovers known ratings).
"""

from __future__ import annotations

import math

import numpy as np

BASE = 1500.0   #: rating of the reference player (the scale's anchor)
SCALE = 400.0   #: Elo points per factor 10 in the odds


def placings(finish_time: np.ndarray, gates: np.ndarray) -> np.ndarray:
    """(R, N) finish times (nan = did not finish) and gates passed -> (R, N) int places (1 = first)."""
    ft = np.asarray(finish_time, dtype=np.float64)
    done = ~np.isnan(ft)
    # one sort key: finished drones by time, below every unfinished one; unfinished by gates, descending
    key = np.where(done, np.round(np.nan_to_num(ft) / 1e-3) * 1e-3, 1e9 - np.asarray(gates, dtype=np.float64))
    return 1 + (key[:, None, :] < key[:, :, None]).sum(-1)    # 1 + number of drones strictly ahead


def winners(finish_time: np.ndarray, places: np.ndarray) -> np.ndarray:
    """(R,) index of the drone that won each race, -1 where nobody finished or first place is shared."""
    first = (places == 1) & ~np.isnan(np.asarray(finish_time, dtype=np.float64))
    return np.where(first.sum(-1) == 1, first.argmax(-1), -1)


def pairwise(places: np.ndarray, who: np.ndarray, players: int) -> tuple[np.ndarray, np.ndarray]:
    """(wins (P, P), games (P, P)) over the races: wins[i, j] = times player i placed ahead of j
    (+0.5 per shared place); who (R, N) the player flying each drone. A player meeting itself (a
    policy entered twice) is not counted."""
    wins = np.zeros((players, players))
    games = np.zeros((players, players))
    r, n = places.shape
    for a in range(n):
        for b in range(n):
            if a == b:
                continue
            i, j = who[:, a], who[:, b]
            score = np.where(places[:, a] < places[:, b], 1.0, np.where(places[:, a] == places[:, b], 0.5, 0.0))
            keep = i != j
            np.add.at(wins, (i[keep], j[keep]), score[keep])
            np.add.at(games, (i[keep], j[keep]), 1.0)
    return wins, games


def fit_ratings(wins: np.ndarray, games: np.ndarray, prior_games: float = 1.0, iters: int = 10000,
                tol: float = 1e-10) -> np.ndarray:
    """(P,) Elo-scale ratings from pairwise wins and games (both counted from each side, as
    ``pairwise`` gives them): Bradley-Terry maximum likelihood by MM, with the reference prior."""
    p = wins.shape[0]
    w = wins.sum(1) + 0.5 * prior_games                  # total wins, with half of the prior games
    strength = np.ones(p)
    for _ in range(iters):
        denom = (games / (strength[:, None] + strength[None, :])).sum(1) + prior_games / (strength + 1.0)
        new = w / denom
        if np.max(np.abs(np.log(new) - np.log(strength))) < tol:
            strength = new
            break
        strength = new
    return BASE + SCALE * np.log10(strength)


def expected_score(r_i: float, r_j: float) -> float:
    """P(i ahead of j) under the fitted model."""
    return 1.0 / (1.0 + math.pow(10.0, (r_j - r_i) / SCALE))
