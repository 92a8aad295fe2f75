"""Evaluation metrics as pure functions over recorded per-step arrays (no simulator, no policy).

A rollout records, for every 50 Hz policy step i (ending at time t[i]) and every world w and drone d:

    active[i, w, d]      bool   the drone was racing during step i (not crashed, not finished, race not over)
    speed[i, w, d]       m/s    |v| at the end of step i
    lap_stamp[i, w, d]   s      exact (2 ms) time a lap was completed during step i, nan otherwise
    contact[i, w, d]     bool   any contact (obstacle or other drone) during step i
    crashed_now[i, w, d] bool   a terminal crash happened during step i
    reason[i, w, d]      int    crash reason (cfrace.sim.simulator.REASONS), 0 without a crash

Definitions (docs/evaluation.md):
- lap time: duration of every completed lap; the first lap is timed from the start (t = 0), later
  laps from the previous lap completion. TTC = mean over all completed laps of all runs.
- average speed: time-weighted mean of |v| over all active steps of all runs, except the step of a
  crash (the simulator stops a crashed drone: its speed reads 0 at the end of that step).
- collisions: rising edges of the contact flag while active (a new obstacle or drone contact) plus
  gate-frame hits (always terminal in the simulator).
- success: all laps completed (no terminal crash, within the time limit).
- race outcome: the first drone to complete the laps wins (finish times to 2 ms; equal = tie,
  a draw); nobody finished: both crashed = draw by double crash, else draw by time-out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cfrace.contract import POLICY_DT
from cfrace.sim.simulator import GATE_FRAME, REASONS


# race outcome codes
EGO_WIN, OPP_WIN, DRAW_CRASH, DRAW_TIMEOUT, DRAW_TIE = 0, 1, 2, 3, 4
OUTCOMES = {EGO_WIN: "ego_win", OPP_WIN: "opp_win", DRAW_CRASH: "draw_both_crashed",
            DRAW_TIMEOUT: "draw_timeout", DRAW_TIE: "draw_tie"}


@dataclass(frozen=True)
class RunSummary:
    """Per (world, drone) results of a rollout; every array is (W, D) unless noted."""

    laps_required: int
    lap_times: np.ndarray     # (W, D, L) s, completed laps in order, nan-padded (L = laps_required)
    laps: np.ndarray          # int, laps completed
    finished: np.ndarray      # bool, all laps completed
    finish_time: np.ndarray   # s, nan unless finished
    crashed: np.ndarray       # bool, terminal crash while racing
    crash_time: np.ndarray    # s, nan unless crashed
    crash_reason: np.ndarray  # int, 0 unless crashed
    timed_out: np.ndarray     # bool, neither finished nor crashed
    contacts: np.ndarray      # int, new contacts (rising edges) while racing
    frame_hits: np.ndarray    # int, gate-frame hits while racing
    flight_time: np.ndarray   # s, time spent racing
    speed_time: np.ndarray    # s, time spent racing, without the crash step
    distance: np.ndarray      # m, path length while racing
    max_speed: np.ndarray     # m/s, nan if never active

    @property
    def collisions(self) -> np.ndarray:
        return self.contacts + self.frame_hits

    @property
    def mean_speed(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.speed_time > 0, self.distance / self.speed_time, np.nan)


def rising_edges(flag: np.ndarray) -> np.ndarray:
    """(T, ...) bool -> (T, ...) bool, True where flag turns on (False before the first step)."""
    prev = np.concatenate([np.zeros_like(flag[:1]), flag[:-1]], axis=0)
    return flag & ~prev


def summarize(active: np.ndarray, speed: np.ndarray, lap_stamp: np.ndarray, contact: np.ndarray,
              crashed_now: np.ndarray, reason: np.ndarray, laps_required: int,
              dt: float = POLICY_DT) -> RunSummary:
    """Per-run results from recorded (T, W, D) arrays (see the module docstring)."""
    active = active.astype(bool)
    t_steps, w, d = active.shape
    stamps = np.where(active, lap_stamp, np.nan)
    laps = (~np.isnan(stamps)).sum(0).astype(np.int64)
    lap_times = np.full((w, d, laps_required), np.nan)
    for wi, di in zip(*np.nonzero(laps)):
        s = stamps[:, wi, di]
        s = s[~np.isnan(s)][:laps_required]
        lap_times[wi, di, :len(s)] = np.diff(np.concatenate([[0.0], s]))
    laps = np.minimum(laps, laps_required)
    finished = laps >= laps_required
    finish_time = np.where(finished, np.nansum(lap_times, axis=-1), np.nan)
    crash = crashed_now.astype(bool) & active
    crashed = crash.any(0)
    t_end = (np.arange(t_steps) + 1) * dt
    first = crash.argmax(0)
    crash_time = np.where(crashed, t_end[first], np.nan)
    crash_reason = np.where(crashed, np.take_along_axis(reason, first[None], 0)[0], 0).astype(np.int64)
    contacts = (rising_edges(contact.astype(bool)) & active).sum(0).astype(np.int64)
    frame_hits = (crash & (reason == GATE_FRAME)).sum(0).astype(np.int64)
    flight_time = active.sum(0) * dt
    moving = active & ~crash
    distance = np.where(moving, speed, 0.0).sum(0) * dt
    with np.errstate(invalid="ignore"):
        max_speed = np.where(moving.any(0), np.where(moving, speed, -np.inf).max(0), np.nan)
    return RunSummary(laps_required, lap_times, laps, finished, finish_time, crashed, crash_time, crash_reason,
                      ~finished & ~crashed, contacts, frame_hits, flight_time, moving.sum(0) * dt, distance,
                      max_speed)


def _mean(x: np.ndarray) -> float | None:
    x = np.asarray(x, dtype=np.float64)
    x = x[~np.isnan(x)]
    return float(x.mean()) if x.size else None


def solo_metrics(s: RunSummary, runs: np.ndarray | slice = slice(None), drone: int = 0) -> dict:
    """The single-agent table row of the runs ``runs`` (world indices) of drone ``drone``."""
    pick = lambda a: a[runs, drone]
    lap_times = s.lap_times[runs, drone]                       # (R, L)
    flight, dist = pick(s.speed_time), pick(s.distance)
    reasons = pick(s.crash_reason)[pick(s.crashed)]
    n = int(pick(s.finished).shape[0])
    return {
        "runs": n,
        "success_rate": float(pick(s.finished).mean()) if n else 0.0,
        "lap_time_s": _mean(lap_times),
        "lap_time_std_s": float(np.nanstd(lap_times)) if (~np.isnan(lap_times)).any() else None,
        "first_lap_s": _mean(lap_times[:, 0]),
        "flying_lap_s": _mean(lap_times[:, 1:]) if lap_times.shape[1] > 1 else None,
        "best_lap_s": float(np.nanmin(lap_times)) if (~np.isnan(lap_times)).any() else None,
        "avg_speed_mps": float(dist.sum() / flight.sum()) if flight.sum() > 0 else None,
        "max_speed_mps": float(np.nanmax(pick(s.max_speed))) if (~np.isnan(pick(s.max_speed))).any() else None,
        "collisions": int(pick(s.collisions).sum()),
        "contacts": int(pick(s.contacts).sum()),
        "frame_hits": int(pick(s.frame_hits).sum()),
        "crashes": int(pick(s.crashed).sum()),
        "crash_reasons": {REASONS[int(k)]: int((reasons == k).sum()) for k in np.unique(reasons)},
        "timeouts": int(pick(s.timed_out).sum()),
        "laps_completed": int(pick(s.laps).sum()),
    }


def race_outcomes(finish_time: np.ndarray, crashed: np.ndarray) -> np.ndarray:
    """(R, 2) finish times (nan = not finished) and crash flags of [ego, opp] -> (R,) outcome codes.

    The first drone to complete the laps wins (also when the other crashed earlier); equal finish
    times are a tie; nobody finished: both crashed -> DRAW_CRASH, otherwise (at least one drone
    still flying at the time limit) -> DRAW_TIMEOUT."""
    finish_time = np.asarray(finish_time, dtype=np.float64)
    crashed = np.asarray(crashed, dtype=bool)
    ft = np.where(np.isnan(finish_time), np.inf, finish_time)
    out = np.where(crashed.all(-1), DRAW_CRASH, DRAW_TIMEOUT)
    out = np.where(ft[:, 0] < ft[:, 1], EGO_WIN, out)
    out = np.where(ft[:, 1] < ft[:, 0], OPP_WIN, out)
    out = np.where(np.isfinite(ft[:, 0]) & (ft[:, 0] == ft[:, 1]), DRAW_TIE, out)
    return out.astype(np.int64)


def race_rates(outcomes: np.ndarray) -> dict:
    """Win / draw rates and counts of a set of race outcomes."""
    n = max(int(outcomes.shape[0]), 1)
    counts = {name: int((outcomes == code).sum()) for code, name in OUTCOMES.items()}
    wins_e, wins_o = counts["ego_win"], counts["opp_win"]
    return {"ego_win_rate": wins_e / n, "opp_win_rate": wins_o / n,
            "draw_rate": (outcomes.shape[0] - wins_e - wins_o) / n, "counts": counts}


def speed_stats(speed: np.ndarray, mask: np.ndarray) -> dict:
    """Max and time-weighted mean speed (m/s) over the steps where ``mask``; None when empty."""
    v = speed[mask.astype(bool)]
    if v.size == 0:
        return {"max_mps": None, "mean_mps": None, "steps": 0}
    return {"max_mps": float(v.max()), "mean_mps": float(v.mean()), "steps": int(v.size)}


def finish_speed(speed: np.ndarray, lap_stamp: np.ndarray, active: np.ndarray, finished: np.ndarray) -> np.ndarray:
    """(W, D) speed at the step of the final lap completion (nan unless finished): the paper's
    final-gate speed. Arrays (T, W, D); ``finished`` (W, D)."""
    stamped = active.astype(bool) & ~np.isnan(lap_stamp)
    last = np.where(stamped.any(0), (stamped.shape[0] - 1) - stamped[::-1].argmax(0), 0)
    v = np.take_along_axis(speed, last[None], 0)[0]
    return np.where(finished, v, np.nan)
