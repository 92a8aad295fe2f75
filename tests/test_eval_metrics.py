"""Evaluation metrics on scripted per-step arrays (no simulator, no policy): lap times, speeds,
collisions, success, race outcome rules and their symmetry under swapped slots."""

from __future__ import annotations

import numpy as np
import pytest

from cfrace.evaluate.metrics import (DRAW_CRASH, DRAW_TIE, DRAW_TIMEOUT, EGO_WIN, OPP_WIN, finish_speed,
                                     race_outcomes, race_rates, rising_edges, solo_metrics, speed_stats, summarize)
from cfrace.sim.simulator import ARENA, FLOOR, GATE_FRAME

DT = 0.02


class Script:
    """Per-step arrays (T, W, D) built up by hand."""

    def __init__(self, steps: int, worlds: int = 1, drones: int = 1):
        shape = (steps, worlds, drones)
        self.active = np.ones(shape, bool)
        self.speed = np.zeros(shape, np.float32)
        self.lap_stamp = np.full(shape, np.nan, np.float32)
        self.contact = np.zeros(shape, bool)
        self.crashed_now = np.zeros(shape, bool)
        self.reason = np.zeros(shape, np.int8)

    def lap(self, t: float, w: int = 0, d: int = 0):
        self.lap_stamp[int(t / DT - 1e-6), w, d] = t  # the step that ends at or after t

    def crash(self, step: int, reason: int, w: int = 0, d: int = 0):
        self.crashed_now[step, w, d] = True
        self.reason[step, w, d] = reason
        self.active[step + 1:, w, d] = False

    def summary(self, laps: int):
        return summarize(self.active, self.speed, self.lap_stamp, self.contact, self.crashed_now, self.reason, laps, DT)


def test_lap_times_speed_and_finish_of_a_scripted_run():
    s = Script(700)
    s.speed[:200] = 3.0
    s.speed[200:] = 5.0
    for t in (4.01, 8.53, 12.0):
        s.lap(t)
    s.active[600:] = False          # finished after the step ending at 12.0 s
    s.lap(13.0)                      # a lap after the finish (not racing) does not count
    r = s.summary(laps=3)
    np.testing.assert_allclose(r.lap_times[0, 0], [4.01, 4.52, 3.47], atol=1e-5)
    assert r.finished[0, 0] and r.laps[0, 0] == 3
    assert r.finish_time[0, 0] == pytest.approx(12.0, abs=1e-5)
    assert not r.crashed[0, 0] and not r.timed_out[0, 0]
    assert r.flight_time[0, 0] == pytest.approx(600 * DT)
    assert r.mean_speed[0, 0] == pytest.approx((200 * 3.0 + 400 * 5.0) / 600)
    assert r.max_speed[0, 0] == pytest.approx(5.0)
    assert r.distance[0, 0] == pytest.approx((200 * 3.0 + 400 * 5.0) * DT)


def test_collisions_count_new_contacts_and_gate_frame_hits_while_racing():
    s = Script(100)
    s.speed[:] = 3.0
    s.speed[50:] = 0.0                           # the crash step and after: the drone is stopped
    s.contact[[3, 4, 5, 9, 20], 0, 0] = True     # two separate contacts: 3-5 and 9, then 20
    s.crash(50, GATE_FRAME)
    s.contact[60:70, 0, 0] = True                # after the crash: ignored
    r = s.summary(laps=1)
    assert r.contacts[0, 0] == 3
    assert r.frame_hits[0, 0] == 1
    assert r.collisions[0, 0] == 4
    assert r.crashed[0, 0] and r.crash_reason[0, 0] == GATE_FRAME
    assert r.crash_time[0, 0] == pytest.approx(51 * DT)
    assert r.flight_time[0, 0] == pytest.approx(51 * DT) and r.speed_time[0, 0] == pytest.approx(50 * DT)
    assert r.mean_speed[0, 0] == pytest.approx(3.0)  # the crash step's 0 is left out
    assert not r.finished[0, 0] and not r.timed_out[0, 0]


def test_other_crashes_are_not_collisions_and_time_out_is_neither():
    s = Script(100, worlds=2)
    s.crash(10, FLOOR, w=0)
    s.lap(1.0, w=1)                              # world 1: one lap of two, then the time limit
    r = s.summary(laps=2)
    assert r.collisions.tolist() == [[0], [0]]
    assert r.crashed[:, 0].tolist() == [True, False]
    assert r.timed_out[:, 0].tolist() == [False, True]
    assert r.laps[:, 0].tolist() == [0, 1] and not r.finished.any()
    assert np.isnan(r.finish_time).all()


def test_rising_edges():
    f = np.array([1, 1, 0, 1, 0, 0, 1], bool)
    assert rising_edges(f).tolist() == [True, False, False, True, False, False, True]


def test_solo_metrics_aggregate_runs_like_table_one():
    s = Script(800, worlds=3)
    s.speed[:] = 4.0
    s.speed[:, 1] = 2.0
    for t in (5.0, 10.0, 15.0):
        s.lap(t, w=0)
    s.active[750:, 0] = False          # finished in the step ending at 15.0 s
    s.lap(6.0, w=1)
    s.crash(399, ARENA, w=1)
    s.crash(99, GATE_FRAME, w=2)
    m = solo_metrics(s.summary(laps=3))
    assert m["runs"] == 3
    assert m["success_rate"] == pytest.approx(1 / 3)
    assert m["lap_time_s"] == pytest.approx((5 + 5 + 5 + 6) / 4)
    assert m["first_lap_s"] == pytest.approx((5 + 6) / 2)
    assert m["flying_lap_s"] == pytest.approx(5.0)
    assert m["best_lap_s"] == pytest.approx(5.0)
    # pooled over active time without the crash steps: world 0 races 750 steps at 4, world 1 399
    # at 2, world 2 99 at 4
    assert m["avg_speed_mps"] == pytest.approx((750 * 4 + 399 * 2 + 99 * 4) / 1248)
    assert m["collisions"] == 1 and m["frame_hits"] == 1
    assert m["crashes"] == 2 and m["crash_reasons"] == {"arena": 1, "gate_frame": 1}
    assert m["laps_completed"] == 4 and m["timeouts"] == 0


def test_solo_metrics_without_any_lap_has_no_lap_time():
    s = Script(50)
    s.crash(10, FLOOR)
    m = solo_metrics(s.summary(laps=3))
    assert m["lap_time_s"] is None and m["success_rate"] == 0.0 and m["crashes"] == 1


NAN = float("nan")


@pytest.mark.parametrize("finish, crashed, expected", [
    ((10.0, 11.0), (False, False), EGO_WIN),        # both finish, ego first
    ((12.5, 11.0), (False, False), OPP_WIN),
    ((NAN, 14.0), (True, False), OPP_WIN),          # ego crashed, the opponent finished later
    ((13.0, NAN), (False, True), EGO_WIN),
    ((NAN, NAN), (True, True), DRAW_CRASH),         # both crashed
    ((NAN, NAN), (False, False), DRAW_TIMEOUT),     # nobody finished in time
    ((NAN, NAN), (True, False), DRAW_TIMEOUT),      # one crashed, the other still flying at the limit
    ((9.0, 9.0), (False, False), DRAW_TIE),
])
def test_race_outcome_rules(finish, crashed, expected):
    out = race_outcomes(np.array([finish]), np.array([crashed]))
    assert out.tolist() == [expected]
    swapped = race_outcomes(np.array([finish[::-1]]), np.array([crashed[::-1]]))
    mirror = {EGO_WIN: OPP_WIN, OPP_WIN: EGO_WIN}.get(expected, expected)
    assert swapped.tolist() == [mirror]


def test_race_rates_count_draws_apart():
    out = np.array([EGO_WIN, EGO_WIN, OPP_WIN, DRAW_CRASH, DRAW_TIMEOUT])
    r = race_rates(out)
    assert r["ego_win_rate"] == pytest.approx(0.4) and r["opp_win_rate"] == pytest.approx(0.2)
    assert r["draw_rate"] == pytest.approx(0.4)
    assert r["counts"] == {"ego_win": 2, "opp_win": 1, "draw_both_crashed": 1, "draw_timeout": 1, "draw_tie": 0}


def test_speed_stats_and_finish_speed():
    s = Script(10, worlds=2)
    s.speed[:, 0, 0] = np.arange(10)
    s.speed[:, 1, 0] = 7.0
    s.lap(0.1, w=0)
    s.lap(0.16, w=0)
    s.active[8:, 0] = False
    st = speed_stats(s.speed, s.active)
    assert st["max_mps"] == 7.0 and st["steps"] == 18
    assert st["mean_mps"] == pytest.approx((sum(range(8)) + 70) / 18)
    assert speed_stats(s.speed, np.zeros_like(s.active))["mean_mps"] is None
    fs = finish_speed(s.speed, s.lap_stamp, s.active, np.array([[True], [False]]))
    assert fs[0, 0] == 7.0 and np.isnan(fs[1, 0])   # step 7 ends at 0.16 s
