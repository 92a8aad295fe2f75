"""The simulated Crazyflies' physics (simcf OneWorld) is the training simulator itself: the same
states as a Simulator stepped with the same commands, bit for bit, and the simulator's rules
(gate pass, frame hit, obstacles, drone contacts, floor, arena) seen through it."""

import math

import numpy as np
import pytest
import torch

from cfrace.drone import load_profile
from cfrace.errors import ConfigError
from cfrace.sim.simulator import ARENA, CEILING, FLOOR, GATE_FRAME, CrashRules, Simulator
from cfrace.simcf.physics import make_physics
from cfrace.track import load_track


def run_both(track, profile, pos, vel, steps, thrust_fn, rates_fn, rules=CrashRules()):
    """Step simcf's physics and a Simulator with the same commands in chunks of 10 substeps; compare
    every chunk exactly."""
    d = len(pos)
    ts = Simulator(track, profile, 1, d, rules=rules, threads=1)
    ts.reset(torch.zeros(1, dtype=torch.int64), torch.tensor(np.asarray(pos)[None], dtype=torch.float32),
             torch.tensor(np.asarray(vel)[None], dtype=torch.float32))
    ns, backend = make_physics(track, profile, d, crash_rules=rules)
    assert backend == ts.backend
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (d, 1))
    ns.reset(pos, vel, quat, np.zeros(d, np.int64))
    for k in range(steps):
        t = k * 0.02
        thrust, rates = np.asarray(thrust_fn(t), float), np.asarray(rates_fn(t), float)
        ts.step(torch.tensor(thrust[None], dtype=torch.float32), torch.tensor(rates[None], dtype=torch.float32), 10)
        ns.step(thrust, rates, 10)
        down = ts.race.crashed[0]   # simcf puts a crashed drone on the floor
        ts.state.pos[0, down, 2] = ts.z_rest
        for name in ("pos", "vel", "quat", "omega", "crashed", "reason"):
            np.testing.assert_array_equal(getattr(ns, name), getattr(ts, name)[0].numpy(),
                                          err_msg=f"{name} differs at t={t + 0.02:.2f} s")
    return ts, ns


def test_gate_pass_and_frame_hit():
    track, profile = load_track("complex"), load_profile("cf2x_paper")
    gx, gy, gz, yaw = track.gates[0]
    n = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    lat = np.array([-n[1], n[0], 0.0])
    g = np.array([gx, gy, gz])
    pos = [g + 0.6 * n, g + 0.6 * n + 0.45 * lat + np.array([0, 0, 0.1])]
    vel = [-3.0 * n, -3.0 * n]
    w = profile.weight
    ts, ns = run_both(track, profile, np.array(pos), np.array(vel), 20,
                     lambda t: [w, w * 1.05],
                     lambda t: [[0.4 * math.sin(9 * t), 0.3 * math.cos(7 * t), 0.5], [0.2, -0.3 * math.sin(5 * t), 0.0]])
    assert ts.race.gates_passed[0].tolist() == [1, 0] and ts.race.target[0].tolist() == [1, 0]
    assert list(ns.crashed) == [False, True] and ns.reason[1] == GATE_FRAME


def test_obstacle_drone_contacts_and_floor():
    track, profile = load_track("complex"), load_profile("cf2x_paper")
    pos = np.array([[0.0, 1.3, 1.0], [3.0, -3.0, 1.0], [3.4, -3.0, 1.02], [-4.0, -6.0, 0.3], [-4.0, -7.0, 0.08]])
    vel = np.array([[0.3, -2.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    w = profile.weight
    # drone 0 hits the wall, then rolls away from it
    _, ns = run_both(track, profile, pos, vel, 25, lambda t: [w, w, w, 0.0, 0.0],
                     lambda t: [[-1.5 if 0.1 <= t < 0.2 else 0.0, 0.0, 0.0]] + [[0.0, 0.0, 0.3 * math.sin(4 * t)]] * 4)
    assert ns.pos[0][1] > 1.05 + profile.collision_radius - 1e-6          # pushed out of the wall
    assert ns.crashed[3] and ns.reason[3] == FLOOR                        # fast impact
    assert not ns.crashed[4] and ns.pos[4][2] == pytest.approx(profile.collision_box[2] / 2)  # soft landing
    assert ns.vel[1][0] < 0.5 and ns.vel[2][0] > -0.5                     # the two drones bounced


def test_floor_grace_and_arena_rules():
    track, profile = load_track("lemniscate"), load_profile("cf2x_paper")
    pos = np.array([[0.0, 3.0, 0.3], [2.3, 4.0, 1.0], [-1.0, 8.5, 2.9]])
    vel = np.array([[0.0, 0.0, -0.5], [2.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    w = profile.weight
    _, ns = run_both(track, profile, pos, vel, 25, lambda t: [w * 0.9, w, w * 1.1],
                     lambda t: [[0.0, 0.0, 0.0]] * 3, rules=CrashRules(floor_grace_s=0.3))
    assert ns.crashed.all() and list(ns.reason) == [FLOOR, ARENA, CEILING]


def test_no_other_physics():
    track, profile = load_track("lemniscate"), load_profile("cf2x_paper")
    with pytest.raises(ConfigError) as e:
        make_physics(track, profile, 2, backend="numpy")
    assert "numpy" in str(e.value) and "\n" not in str(e.value)
