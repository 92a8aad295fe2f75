"""RaceEnv: shapes, spawns, rewards on scripted situations, resets, exact state round trip."""

from __future__ import annotations

import torch

from cfrace.drone import load_profile
from cfrace.contract.observations import build_observation, build_observations, layout_for
from cfrace.env.race_env import RaceEnv
from cfrace.env.rewards import RewardInputs, leading, overtaking, reward_terms
from cfrace.track import load_track

PROFILE = load_profile("cf2x_paper")
LEM = load_track("lemniscate")


def hover_actions(env):
    a = torch.zeros(env.num_envs, env.num_agents, 4)
    a[..., 0] = 2.0 / PROFILE.max_thrust_weights - 1.0
    return a


def test_shapes_for_every_method():
    for method, agents, dim in (("ours", 2, 42), ("dm", 2, 42), ("ds", 1, 36), ("ss", 1, 36)):
        env = RaceEnv(LEM, PROFILE, num_envs=8, method=method, obstacles=False)
        obs, critic = env.reset()
        assert obs.shape == (8, agents, dim) and critic.shape == (8, agents, dim * agents)
        res = env.step(hover_actions(env))
        assert res.reward.shape == (8, agents) and set(res.terms) >= {"rate", "contact", "crash"}
    env = RaceEnv(LEM, PROFILE, num_envs=4, method="ours", obstacles=True)
    assert env.reset()[0].shape == (4, 2, 45)


def test_spawns_are_safe_and_before_the_target_gate():
    for track in ("lemniscate", "complex"):
        env = RaceEnv(load_track(track), PROFILE, num_envs=512, method="ours", obstacles=True, seed=1)
        env.reset()
        res = env.step(hover_actions(env))
        assert not res.terminated.any(), track
        gate = env.gates[env.sim.target]
        yaw = gate[..., 3]
        along = (env.sim.pos[..., 0] - gate[..., 0]) * torch.cos(yaw) + (env.sim.pos[..., 1] - gate[..., 1]) * torch.sin(yaw)
        assert (along > 0).all(), track  # on the +n side: the gate is ahead


def test_opponent_stagger_puts_one_drone_further_back_at_random(tmp_path):
    text = (LEM.source and open(LEM.source).read()).replace(
        "  opponent_offset: 0.4", "  opponent_stagger: 0.8\n  opponent_offset: 0.4")
    path = tmp_path / "stagger.yaml"
    path.write_text(text)
    trk = load_track(path)
    assert trk.spawn.opponent_stagger == 0.8 and LEM.spawn.opponent_stagger == 0.0
    for track, stagger in ((trk, 0.8), (LEM, 0.0)):
        env = RaceEnv(track, PROFILE, num_envs=400, method="ours", obstacles=False, start="gate", seed=3)
        pos, _, g = env.spawn(400)
        gate = env.gates[g]
        n = torch.stack([torch.cos(gate[:, 3]), torch.sin(gate[:, 3])], -1)
        along = ((pos[..., :2] - gate[:, None, :2]) * n[:, None]).sum(-1)          # (n, 2) m before the gate
        diff = along[:, 0] - along[:, 1]
        assert torch.allclose(diff.abs(), torch.full_like(diff, stagger), atol=1e-4)
        assert along.min() >= track.spawn.gate_distance[0] - 1e-4                  # the front drone keeps its distance
        if stagger:
            assert 0.35 < (diff > 0).float().mean() < 0.65                          # either slot may be behind
        side = torch.stack([-torch.sin(gate[:, 3]), torch.cos(gate[:, 3])], -1)
        lateral = ((pos[:, 0, :2] - pos[:, 1, :2]) * side).sum(-1).abs()
        assert torch.allclose(lateral, torch.full_like(lateral, 0.4), atol=1e-4)


def test_crash_terminates_once_and_world_resets_when_both_done():
    env = RaceEnv(LEM, PROFILE, num_envs=2, method="ours", obstacles=False, randomize=False)
    env.reset()
    a = hover_actions(env)
    a[0, 0, 0] = -1.0  # world 0, drone 0: motors off -> falls -> floor crash after the grace time
    seen = 0
    for _ in range(100):
        res = env.step(a)
        seen += int(res.terminated[0, 0])
        if res.terminated[0, 0]:
            assert res.terms["crash"][0, 0].item() == -2.0
        if seen:
            break
    assert seen == 1
    res = env.step(a)
    assert not res.alive[0, 0] and res.alive[0, 1] and res.reward[0, 0] == 0.0
    assert not res.terminated[0, 0]


def test_timeout_truncates_alive_agents():
    env = RaceEnv(LEM, PROFILE, num_envs=2, method="ds", obstacles=False, episode_s=0.1, randomize=False,
                  start="gate")
    env.reset()
    for i in range(5):
        res = env.step(hover_actions(env))
    assert res.truncated.all() and not res.terminated.any()


def test_reward_terms_on_scripted_inputs():
    e = 1
    z = torch.zeros(e, 2)
    act = torch.zeros(e, 2, 4)
    act[..., 1] = 1.0
    act[..., 3] = 1.0
    x = RewardInputs(act, torch.tensor([[1, 1]]), torch.tensor([[True, False]]), torch.tensor([[True, False]]),
                     torch.tensor([[False, True]]), torch.tensor([[False, True]]), torch.tensor([[0.1, -0.2]]),
                     torch.tensor([[0.3, -0.3]]), 0.02)
    ours = reward_terms("ours", x)
    assert ours["gate"].tolist() == [[10.0, 5.0]]  # leading pays 10, else 5
    assert ours["lap"].tolist() == [[50.0, 0.0]]
    assert torch.allclose(ours["rate"], torch.tensor([[-(0.15 + 0.05) * 0.02] * 2]))
    assert torch.allclose(ours["contact"], torch.tensor([[0.0, -0.1]]))
    assert torch.allclose(ours["crash"], torch.tensor([[0.0, -2.0]]))
    ds = reward_terms("ds", x)
    assert torch.allclose(ds["progress"], torch.tensor([[5.0, -10.0]]))
    assert torch.allclose(ds["crash"], torch.tensor([[0.0, -10.0]]))
    assert torch.allclose(ds["contact"], torch.tensor([[0.0, -1.0]]))
    assert "overtake" not in ds and "gate" not in ds
    dm = reward_terms("dm", x)
    assert torch.allclose(dm["overtake"], torch.tensor([[15.0, -15.0]]))
    ss = reward_terms("ss", x)
    assert ss["gate"].tolist() == [[10.0, 10.0]]


def test_leading_rule():
    gp = torch.tensor([[3, 2], [2, 2], [2, 2]])
    d = torch.tensor([[5.0, 1.0], [2.0, 1.0], [1.0, 2.0]])
    alive = torch.tensor([[True, True], [True, True], [False, True]])
    assert leading(gp, d, alive).tolist() == [[True, False], [False, True], [False, True]]


def test_overtaking_window():
    prev = torch.tensor([[0.0, 3.0], [0.0, 20.0]])
    now = torch.tensor([[1.0, 3.5], [1.0, 20.0]])
    ot = overtaking(now, prev)
    assert torch.allclose(ot[0], torch.tensor([0.5, -0.5]))  # gained 0.5 m on an opponent 3 m ahead
    assert torch.allclose(ot[1], torch.tensor([0.0, 0.0]))  # opponent 20 m ahead: outside d_max


def test_lap_bonus_paid_once_per_lap_per_race():
    env = RaceEnv(LEM, PROFILE, num_envs=1, method="ours", obstacles=False, randomize=False)
    env.reset()
    paid = []
    # drive both drones' race state: drone 0 completes lap 1, then drone 1 completes lap 1
    for who in (0, 1):
        env.sim.race.gates_passed[0, who] = 5
        env.sim.race.laps[0, who] = 0
    # use the env's own rule through a scripted step: teleport through the next gate
    for who in (0, 1):
        tgt = int(env.sim.race.target[0, who])
        gate = env.gates[tgt]
        n = torch.stack([torch.cos(gate[3]), torch.sin(gate[3]), torch.tensor(0.0)])
        env.sim.state.pos[0, who] = gate[:3] + 0.05 * n
        env.sim.state.vel[0, who] = -4.0 * n
        other = 1 - who
        env.sim.state.pos[0, other] = torch.tensor([0.5 + other, 8.5, 1.0])
        env.sim.state.vel[0, other] = 0.0
        env.prev_pos = env.sim.pos.clone()
        res = env.step(hover_actions(env))
        paid.append(res.terms["lap"][0].tolist())
    assert paid[0] == [50.0, 0.0]
    assert paid[1] == [0.0, 0.0]  # the second drone finishing lap 1 gets no bonus


def test_observations_match_manual_layout():
    env = RaceEnv(LEM, PROFILE, num_envs=3, method="ours", obstacles=True)
    obs, critic = env.reset()
    s = env.sim
    lay = layout_for(True, True)
    one = build_observation(s.pos[:, 0], s.vel[:, 0], s.rot()[:, 0], s.race.target[:, 0], s.gate_corners, lay,
                            s.pos[:, 1], s.vel[:, 1])
    assert torch.equal(one, obs[:, 0])
    assert torch.equal(critic[:, 0], torch.cat([obs[:, 0], obs[:, 1]], -1))
    assert torch.equal(obs[:, 0, :3], s.pos[:, 0])


def test_state_dict_round_trip_is_exact():
    a = RaceEnv(LEM, PROFILE, num_envs=16, method="ours", obstacles=False, seed=4)
    a.reset()
    g = torch.Generator().manual_seed(0)
    acts = [hover_actions(a) + 0.3 * torch.randn(16, 2, 4, generator=g) for _ in range(30)]
    for x in acts[:10]:
        a.step(x)
    snap = a.state_dict()
    b = RaceEnv(LEM, PROFILE, num_envs=16, method="ours", obstacles=False, seed=99)
    b.reset()
    b.load_state_dict(snap)
    for x in acts[10:]:
        ra, rb = a.step(x), b.step(x)
        assert torch.equal(ra.obs, rb.obs) and torch.equal(ra.reward, rb.reward)


def test_random_phase_spreads_the_first_time_outs():
    track, prof = load_track("lemniscate"), load_profile("cf2x_paper")
    plain = RaceEnv(track, prof, num_envs=256, method="ds", obstacles=False, episode_s=2.0)
    plain.reset()
    assert int(plain.steps.max()) == 0
    env = RaceEnv(track, prof, num_envs=256, method="ds", obstacles=False, episode_s=2.0, random_phase=True)
    env.reset()
    steps = env.steps
    assert int(steps.min()) >= 0 and int(steps.max()) < env.max_steps and len(set(steps.tolist())) > 50
    # the worlds one step short of the limit time out in the first step (and only those)
    last = steps == env.max_steps - 1
    res = env.step(torch.zeros(256, 1, 4))
    assert bool(last.any())
    assert torch.equal(res.truncated[:, 0], last & ~res.terminated[:, 0])


def test_flight_obs_observes_the_pose_difference_and_floors_the_thrust():
    """flight_obs splits each policy step at 10 ms: the dynamics are the same (hover commands), the
    observed velocity is the last 10-ms pose difference (as the flight loop's estimator computes it
    from 100 Hz mocap), and thrust never goes below the firmware's least non-zero command."""
    from cfrace.contract.actions import FIRMWARE_MIN_THRUST_COUNTS
    from cfrace.contract.observations import body_frame

    track, prof = load_track("lemniscate"), load_profile("cf2x_paper")
    kw = dict(num_envs=3, method="ds", obstacles=False, seed=5, randomize=False, start="gate")
    plain, flight = RaceEnv(track, prof, **kw), RaceEnv(track, prof, flight_obs=True, **kw)
    o_plain, _ = plain.reset()
    o_flight, _ = flight.reset()
    assert torch.equal(o_plain[..., 3:], o_flight[..., 3:]) and not o_flight[..., :3].any()   # at rest
    hover = torch.zeros(3, 1, 4)
    hover[..., 0] = 2.0 / prof.max_thrust_weights - 1.0          # thrust = weight
    hover[..., 2] = 0.3                                            # and a pitch rate: it moves
    for _ in range(5):
        r_plain, r_flight = plain.step(hover), flight.step(hover)
    assert torch.equal(plain.sim.pos, flight.sim.pos)             # 5 + 5 substeps = 10 substeps
    s = flight.sim
    v_diff = (s.pos - flight.mid_pos) / 0.01
    expect = body_frame(s.rot(), v_diff)
    torch.testing.assert_close(r_flight.obs[..., :3], expect, rtol=0, atol=1e-5)
    assert not torch.allclose(r_flight.obs[..., :3], r_plain.obs[..., :3], atol=1e-4)   # a lagged velocity
    sent = []
    step = flight.sim.step
    flight.sim.step = lambda thrust, rates, n: (sent.append(thrust.clone()), step(thrust, rates, n))[1]
    flight.step(torch.full((3, 1, 4), -1.0))                       # zero thrust asked
    floor = float(prof.thrust_curve.to_newtons(FIRMWARE_MIN_THRUST_COUNTS))
    assert len(sent) == 2 and all(torch.allclose(t, torch.full_like(t, floor)) for t in sent) and floor > 0
