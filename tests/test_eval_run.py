"""Evaluation through the real pipeline: simulator, onnxruntime, observation and action maps.

A straight two-gate track and tiny linear ONNX policies that hold a forward tilt (from the rotation
matrix in their own observation) and fly straight through both gates: one lap, a known lap time,
and races whose outcome is known in advance (faster wins, a lane through a gate frame crashes)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from cfrace.drone import DEFAULT_PROFILE, load_profile
from cfrace.contract.actions import action_map_constants
from cfrace.contract.observations import LAYOUTS
from cfrace.evaluate.entrants import load_entrant, load_entrants
from cfrace.evaluate.metrics import DRAW_CRASH, DRAW_TIE, DRAW_TIMEOUT, EGO_WIN, OPP_WIN, race_outcomes
from cfrace.evaluate.rollout import Starts, rollout, start_poses
from cfrace.evaluate.single import evaluate
from cfrace.sim.simulator import ARENA, GATE_FRAME, LONG_CONTACT
from cfrace.track import load_track

from policyfiles import make_test_policy

PROFILE = load_profile(DEFAULT_PROFILE)
G = 9.81

TRACK_YAML = """\
name: straight
gates:
  - [0.0, 0.0, 1.0, 0.0]
  - [-3.0, 0.0, 1.0, 0.0]
obstacles:
  - {center: [-1.5, 0.3], size: [0.1, 0.1, 8.0], yaw: 0.0}
arena:
  x: [-6.0, 3.0]
  y: [-3.0, 3.0]
  z_max: 3.0
"""


def tilt_policy(path: Path, tilt_deg: float, layout: str = "solo36", track: str = "straight",
                obstacles: bool = False) -> Path:
    """A linear policy that flies along world -x at any heading: body rates turn the body z axis
    toward d = (-sin tilt, 0, cos tilt) (d in body coordinates, R^T d, is linear in the rotation
    matrix of the observation); thrust 1 / cos(current tilt) weights, linearised in R22."""
    from cfrace.policygraph import build_model
    import onnx

    lay = LAYOUTS[layout]
    d = lay.dim
    r = lambda i, j: (3 if lay.world_position else 0) + 3 + 3 * i + j   # R[i][j] in the observation
    th = math.radians(tilt_deg)
    s, c = math.sin(th), math.cos(th)
    k = 8.0 / math.radians(PROFILE.max_rates_deg[0])  # 8 rad/s of rate per rad of error
    w = np.zeros((4, d), np.float32)
    b = np.zeros(4, np.float32)
    slope = (1.0 / c - 1.0) / (1.0 - c)                # weights = 1 + slope (1 - R22)
    t = 2.0 / PROFILE.max_thrust_weights
    b[0], w[0, r(2, 2)] = t * (1.0 + slope) - 1.0, -t * slope
    w[2, r(0, 0)], w[2, r(2, 0)] = -k * s, k * c      # pitch rate = k (R^T d)_x
    w[1, r(0, 1)], w[1, r(2, 1)] = k * s, -k * c      # roll rate = -k (R^T d)_y
    meta = {"method": "ours" if lay.opponent else "ds", "track": track, "obstacles": obstacles,
            "obs_layout": layout, "obs_dim": d, **action_map_constants(PROFILE), "policy_hz": 50.0,
            "drone_profile": PROFILE.name, "train_steps": 0, "seed": 0, "cfrace_version": "test"}
    onnx.save_model(build_model([("linear", w, b)], None, None, meta, d), str(path))
    return path


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("eval")
    (tmp / "straight.yaml").write_text(TRACK_YAML)
    track = load_track(tmp / "straight.yaml")
    pol = {"fast": tilt_policy(tmp / "fast.onnx", 30.0), "slow": tilt_policy(tmp / "slow.onnx", 15.0),
           "fast42": tilt_policy(tmp / "fast42.onnx", 30.0, "race42"),
           "hover": make_test_policy(tmp / "hover.onnx", "solo36", "straight", False, "hover"),
           "nan": make_test_policy(tmp / "nan.onnx", "solo36", "straight", False, "nan"),
           "fast_obst": tilt_policy(tmp / "fast_obst.onnx", 30.0, "solo39_obstacles", obstacles=True)}
    return tmp, track, pol


def starts(lanes):
    """Level starts facing +x at x = 1, z = 1, one y lane per drone per world: lanes (W, D)."""
    lanes = torch.tensor(lanes, dtype=torch.float32)
    w, d = lanes.shape
    pos = torch.stack([torch.ones(w, d), lanes, torch.ones(w, d)], -1)
    quat = torch.zeros(w, d, 4)
    quat[..., 0] = 1.0
    return Starts(pos, quat, torch.zeros(w, d, dtype=torch.int64))


def straight_time(tilt_deg: float, dist: float = 4.0) -> float:
    return math.sqrt(2.0 * dist / (G * math.tan(math.radians(tilt_deg))))


def test_solo_lap_time_speed_and_success_through_the_pipeline(setup):
    _, track, pol = setup
    ents = load_entrants([str(pol["fast"]), str(pol["slow"]), str(pol["hover"])], track, False)
    rec = rollout(track, PROFILE, False, ents, np.array([[0], [1], [2]]), starts([[0.0], [0.0], [0.0]]), laps=1,
                  time_limit_s=3.0, record=(0,))
    s = rec.summary()
    assert s.finished[:, 0].tolist() == [True, True, False]
    assert s.timed_out[2, 0] and not s.crashed.any()
    for i, tilt in ((0, 30.0), (1, 15.0)):     # drag and the tilt-up time make it a little slower
        assert straight_time(tilt) < s.lap_times[i, 0, 0] < 1.2 * straight_time(tilt) + 0.15
        assert s.mean_speed[i, 0] == pytest.approx(4.0 / s.lap_times[i, 0, 0], rel=0.1)
    assert s.lap_times[0, 0, 0] < s.lap_times[1, 0, 0]
    assert rec.t[-1] == pytest.approx(3.0)      # the hovering run went to the time limit
    xyz = rec.pos[rec.active[:, 0, 0], 0, 0]
    assert xyz[-1, 0] < -3.0 and abs(xyz[:, 1]).max() < 0.1 and abs(xyz[:, 2] - 1.0).max() < 0.1


def test_race_outcomes_through_the_pipeline(setup):
    _, track, pol = setup
    ents = load_entrants([str(pol["fast"]), str(pol["slow"]), str(pol["hover"]), str(pol["fast42"])], track, False)
    assign = np.array([[0, 1], [1, 0], [1, 0], [0, 0], [2, 2], [0, 0], [3, 1]])
    lanes = [[0.2, -0.2],    # fast vs slow: ego wins
             [0.2, -0.2],    # slow vs fast: opp wins
             [0.2, -0.6],    # slow vs fast, whose lane hits the gate frame: the slow ego still wins
             [0.6, -0.6],    # both through the frame: draw by double crash
             [0.2, -0.2],    # hover vs hover: draw by time-out
             [0.2, -0.2],    # the same policy in mirrored lanes: a tie
             [0.2, -0.2]]    # a 42-D multi-agent policy against a 36-D single-agent one
    rec = rollout(track, PROFILE, False, ents, assign, starts(lanes), laps=1, time_limit_s=3.0)
    s = rec.summary()
    out = race_outcomes(s.finish_time, s.crashed).tolist()
    assert out == [EGO_WIN, OPP_WIN, EGO_WIN, DRAW_CRASH, DRAW_TIMEOUT, DRAW_TIE, EGO_WIN]
    assert s.crash_reason[2, 1] == GATE_FRAME and s.frame_hits[2, 1] == 1 and s.collisions[2, 1] == 1
    assert s.crash_reason[3].tolist() == [GATE_FRAME, GATE_FRAME]
    assert s.finish_time[6, 0] == pytest.approx(s.finish_time[0, 0], abs=0.011)  # same flight, other layout


def test_contacts_with_an_obstacle_are_counted(setup):
    _, track, pol = setup
    ents = load_entrants([str(pol["fast_obst"])], track, True)
    rec = rollout(track, PROFILE, True, ents, np.zeros((2, 1), np.int64), starts([[0.3], [-0.2]]), laps=1,
                  time_limit_s=3.0)
    s = rec.summary()
    # lane y = 0.3 runs into the pillar head-on and stays pressed against it: one contact, then the
    # long-contact crash; lane y = -0.2 is clear
    assert s.contacts[:, 0].tolist() == [1, 0] and s.collisions[:, 0].tolist() == [1, 0]
    assert s.crashed[:, 0].tolist() == [True, False] and s.crash_reason[0, 0] == LONG_CONTACT
    assert s.finished[:, 0].tolist() == [False, True]


def test_nan_actions_become_motors_off_and_are_counted(setup):
    _, track, pol = setup
    ents = load_entrants([str(pol["nan"])], track, False)
    rec = rollout(track, PROFILE, False, ents, np.zeros((1, 1), np.int64), starts([[0.0]]), laps=1, time_limit_s=2.0)
    s = rec.summary()
    assert rec.nan_actions[0, 0] > 0
    assert s.crashed[0, 0] and not s.finished[0, 0]


def test_run_leaving_the_arena_after_the_lap_is_a_crash_on_lap_two(setup):
    _, track, pol = setup
    ents = load_entrants([str(pol["fast"])], track, False)
    rec = rollout(track, PROFILE, False, ents, np.zeros((1, 1), np.int64), starts([[0.0]]), laps=2, time_limit_s=4.0)
    s = rec.summary()
    assert s.laps[0, 0] == 1 and s.crashed[0, 0] and s.crash_reason[0, 0] == ARENA
    assert not np.isnan(s.lap_times[0, 0, 0]) and np.isnan(s.lap_times[0, 0, 1])


def test_swapped_starts_mirror_the_slots():
    track = load_track("lemniscate")
    st = start_poses(track, PROFILE, 5, 2, False, seed=3, swap_pairs=True)
    assert st.pos.shape == (5, 2, 3) and st.target.shape == (5, 2)
    for k in (0, 2):
        assert torch.equal(st.pos[k + 1], st.pos[k].flip(0)) and torch.equal(st.quat[k + 1], st.quat[k].flip(0))
        assert torch.equal(st.target[k], st.target[k + 1])
    assert not torch.equal(st.pos[0], st.pos[2])
    again = start_poses(track, PROFILE, 5, 2, False, seed=3, swap_pairs=True)
    assert torch.equal(again.pos, st.pos)           # seeded


def test_ground_starts_are_on_the_floor_before_gate_0():
    from cfrace.errors import ConfigError

    track = load_track("lemniscate")
    st = start_poses(track, PROFILE, 6, 1, False, seed=2, start="ground")
    air = start_poses(track, PROFILE, 6, 1, False, seed=2)
    assert (st.target == 0).all() and not (air.target == 0).all()
    assert float(st.pos[..., 2].max()) < 0.05 < float(air.pos[..., 2].min())
    gate0 = torch.as_tensor(track.gate_array()[0, :2], dtype=torch.float32)
    assert float(torch.linalg.norm(st.pos[:, 0, :2] - gate0, dim=-1).max()) < 1.6
    with pytest.raises(ConfigError, match="--start"):
        start_poses(track, PROFILE, 2, 1, False, seed=2, start="air")


def test_swapped_races_of_one_policy_are_mirror_images(tmp_path):
    """The same (erratic) policy in both slots: race 2k+1 is race 2k with the drones exchanged."""
    track = load_track("lemniscate")
    p = make_test_policy(tmp_path / "r.onnx", "race42", "lemniscate", False, "random", seed=4)
    ents = load_entrants([str(p)], track, False)
    st = start_poses(track, PROFILE, 4, 2, False, seed=1, swap_pairs=True)
    rec = rollout(track, PROFILE, False, ents, np.zeros((4, 2), np.int64), st, laps=1, time_limit_s=1.5,
                  record=(0, 1, 2, 3))
    for k in (0, 2):
        np.testing.assert_allclose(rec.pos[:, k], rec.pos[:, k + 1][:, ::-1], atol=1e-5)
        assert np.array_equal(rec.crashed[:, k], rec.crashed[:, k + 1][:, ::-1])
    assert np.abs(np.diff(rec.pos[:, 0, 0], axis=0)).max() > 0      # it does move


def test_a_multi_agent_policy_flying_alone_sees_its_opponent_crashed_beside_its_start():
    """The opponent of a policy flying alone lies on the floor in the start slot next to it (left in
    even worlds, right in odd ones), where a training race leaves an opponent that crashed at the start."""
    from cfrace.evaluate.rollout import parked_opponents

    track, prof = load_track("complex"), load_profile(DEFAULT_PROFILE)
    starts = start_poses(track, prof, 6, 1, False, seed=3)
    parked = parked_opponents(track, prof, starts)
    assert parked.shape == (6, 3)
    assert torch.allclose(parked[:, 2], torch.full((6,), prof.collision_box[2] / 2))
    gap = parked[:, :2] - starts.pos[:, 0, :2]
    assert torch.allclose(gap.norm(dim=-1), torch.full((6,), track.spawn.opponent_offset), atol=1e-5)
    yaw = torch.as_tensor(track.gate_array()[:, 3], dtype=torch.float32)[starts.target[:, 0]]
    normal = torch.stack([torch.cos(yaw), torch.sin(yaw)], -1)
    assert (gap * normal).sum(-1).abs().max() < 1e-5                       # beside, not ahead or behind
    left = torch.stack([-torch.sin(yaw), torch.cos(yaw)], -1)
    assert torch.equal(torch.sign((gap * left).sum(-1)), torch.tensor([1.0, -1, 1, -1, 1, -1]))
