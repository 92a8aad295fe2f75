"""N-drone races: the opponent rule, observations and critics for N, rewards for N, the start grid,
placings and the rating, the C kernel at 8 drones, `cfrace race --entrants` and `--field`."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
import torch

from cfrace.drone import DEFAULT_PROFILE, load_profile
from cfrace.contract.observations import (OPPONENT_RULES, build_observation, build_observations, choose_opponents,
                                     critic_observations, layout_for)
from cfrace.env.rewards import leading, overtaking
from cfrace.evaluate.rating import expected_score, fit_ratings, pairwise, placings, winners
from cfrace.errors import ConfigError
from cfrace.track import ground_start_positions, load_track, start_grid


@pytest.fixture
def run_cli():
    """cfrace's CLI in this process: run_cli(*args) -> typer's Result (exit_code, output)."""
    from typer.testing import CliRunner

    from cfrace.cli.main import app

    runner = CliRunner()
    return lambda *args: runner.invoke(app, list(args))


def _field(n=4, w=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(w, n, 3, generator=g) * 4
    tp = torch.rand(w, n, generator=g) * 20
    alive = torch.ones(w, n, dtype=torch.bool)
    return pos, tp, alive


@pytest.mark.parametrize("rule", OPPONENT_RULES)
def test_opponent_rules_torch_numpy_agree_and_never_pick_self(rule):
    pos, tp, alive = _field(5, 20)
    alive[3, 1] = False
    t = choose_opponents(pos, tp, alive, rule)
    n = choose_opponents(pos.numpy(), tp.numpy(), alive.numpy(), rule)
    assert np.array_equal(t.numpy(), n)
    assert not (t == torch.arange(5)).any()
    assert not (t[3] == 1).any()   # a crashed drone is never picked while a live one is left


def test_opponent_rules_by_hand():
    # drones on a line: x = 0, 1, 5, 6 m, track positions 0, 1, 5, 6 m
    pos = torch.tensor([[[0.0, 0, 1], [1, 0, 1], [5, 0, 1], [6, 0, 1]]])
    tp = torch.tensor([[0.0, 1.0, 5.0, 6.0]])
    alive = torch.ones(1, 4, dtype=torch.bool)
    assert choose_opponents(pos, tp, alive, "nearest").tolist() == [[1, 0, 3, 2]]
    assert choose_opponents(pos, tp, alive, "ahead").tolist() == [[1, 2, 3, 2]]   # the leader sees who is behind
    assert choose_opponents(pos, tp, alive, "track").tolist() == [[1, 0, 3, 2]]
    alive[0, 3] = False
    assert choose_opponents(pos, tp, alive, "ahead").tolist()[0][:3] == [1, 2, 1]
    # with two drones every rule gives the other one
    for rule in OPPONENT_RULES:
        assert choose_opponents(pos[:, :2], tp[:, :2], alive[:, :2], rule).tolist() == [[1, 0]]
    with pytest.raises(ValueError, match="unknown opponent rule"):
        choose_opponents(pos, tp, alive, "furthest")


def test_n_drone_observation_is_the_two_drone_one_with_the_chosen_opponent():
    track = load_track("lemniscate")
    corners = torch.as_tensor(track.gate_corners(), dtype=torch.float32)
    pos, tp, alive = _field(4, 2)
    vel = torch.randn(2, 4, 3)
    rot = torch.linalg.qr(torch.randn(2, 4, 3, 3))[0]
    target = torch.randint(0, len(track.gates), (2, 4))
    layout = layout_for(True, False)
    opp = choose_opponents(pos, tp, alive, "nearest")
    obs = build_observations(pos, vel, rot, target, corners, layout, opp)
    for w in range(2):
        for i in range(4):
            j = int(opp[w, i])
            ref = build_observation(pos[w, i], vel[w, i], rot[w, i], target[w, i], corners, layout, pos[w, j], vel[w, j])
            assert torch.equal(obs[w, i], ref)
    # two drones, no opponent index: the other drone, as before
    two = build_observations(pos[:, :2], vel[:, :2], rot[:, :2], target[:, :2], corners, layout)
    assert torch.equal(two, build_observations(pos[:, :2], vel[:, :2], rot[:, :2], target[:, :2], corners, layout,
                                               torch.tensor([[1, 0], [1, 0]])))
    with pytest.raises(ValueError, match="needs the opponent"):
        build_observations(pos, vel, rot, target, corners, layout)
    # the critic: own observation, the observed opponent's, then the others by index
    crit = critic_observations(obs, opp)
    d = obs.shape[-1]
    assert crit.shape == (2, 4, 4 * d)
    for w in range(2):
        for i in range(4):
            j = int(opp[w, i])
            rest = [k for k in range(4) if k not in (i, j)]
            assert torch.equal(crit[w, i], torch.cat([obs[w, i], obs[w, j], *(obs[w, k] for k in rest)]))
    assert torch.equal(critic_observations(obs[:, :2], torch.tensor([[1, 0], [1, 0]])), critic_observations(obs[:, :2]))


def test_leading_and_overtaking_for_n_reduce_to_two_drones():
    g = torch.tensor([[3, 5, 5, 1]])
    d = torch.tensor([[0.5, 2.0, 1.0, 0.1]])
    alive = torch.ones(1, 4, dtype=torch.bool)
    assert leading(g, d, alive).tolist() == [[False, False, True, False]]   # first place only
    alive[0, 2] = False
    assert leading(g, d, alive).tolist() == [[False, True, False, False]]
    # two drones: the old rule
    g2, d2, a2 = g[:, :2], d[:, :2], torch.ones(1, 2, dtype=torch.bool)
    assert leading(g2, d2, a2).tolist() == [[False, True]]
    p0, p1 = torch.tensor([[0.0, 3.0, 20.0]]), torch.tensor([[1.0, 3.5, 20.0]])
    three = overtaking(p1, p0)
    # drone 0 gains 0.5 m on drone 1 (inside the window); drone 2 is 19-20 m ahead (outside): mean over 2
    assert three[0, 0].item() == pytest.approx(0.5 / 2)
    # the exact rule: r_i = mean over j of 1[-5 < p_j - p_i < 10] ((p_i - p_j)_t - (p_i - p_j)_(t-1))
    for i in range(3):
        want = sum(((p1[0, i] - p1[0, j]) - (p0[0, i] - p0[0, j])).item()
                   for j in range(3) if j != i and -5 < (p1[0, j] - p1[0, i]).item() < 10) / 2
        assert three[0, i].item() == pytest.approx(want)
    two = overtaking(p1[:, :2], p0[:, :2])
    assert two[0].tolist() == pytest.approx([0.5, -0.5])


def test_start_grid_from_the_track():
    track = load_track("lemniscate")
    sp, gate = track.spawn, track.gate
    assert np.allclose(start_grid(sp, gate, 2), [[-0.2, 0.0], [0.2, 0.0]])
    for n in (3, 4, 8, 16):
        g = start_grid(sp, gate, n)
        assert g.shape == (n, 2)
        assert np.abs(g[:, 0]).max() <= gate.opening / 2            # inside the opening
        dist = np.linalg.norm(g[:, None] - g[None], axis=-1) + np.eye(n) * 9
        assert dist.min() >= sp.opponent_offset - 1e-9               # nobody closer than the offset
        assert abs(g[:, 1].min() + g[:, 1].max()) < 1e-9              # rows centred on the spawn distance
    assert np.allclose(np.unique(start_grid(sp, gate, 4)[:, 1]), [-0.2, 0.2])   # 0.8 and 1.2 m before gate 0
    with pytest.raises(ValueError):
        start_grid(sp, gate, 0)


def test_env_with_four_drones_spawns_a_grid_and_steps():
    from cfrace.env.race_env import RaceEnv

    env = RaceEnv(load_track("lemniscate"), load_profile(DEFAULT_PROFILE), num_envs=8, method="dm", obstacles=False,
                  drones=4, opponent_rule="ahead", start="gate")
    obs, crit = env.reset()
    assert obs.shape == (8, 4, 42) and crit.shape == (8, 4, 168)
    p = env.sim.pos
    dist = torch.cdist(p, p) + torch.eye(4) * 9
    assert dist.min() > 0.39                                          # the grid's 0.4 m
    res = env.step(torch.zeros(8, 4, 4))
    assert set(res.terms) == {"progress", "rate", "contact", "crash", "overtake"}
    assert res.reward.shape == (8, 4)
    with pytest.raises(ValueError, match="multi-agent"):
        RaceEnv(load_track("lemniscate"), load_profile(DEFAULT_PROFILE), num_envs=1, method="ds", obstacles=False,
                drones=4)


def test_starts_of_a_field_stay_inside_the_arena():
    """8 drones on the lemniscate: some gate starts would put the grid's back row behind the arena's
    wall (gate 0 stands 1.5 m from it); those are drawn again. A ground start cannot fit at all."""
    from cfrace.env.race_env import RaceEnv

    track = load_track("lemniscate")
    env = RaceEnv(track, load_profile(DEFAULT_PROFILE), num_envs=1, method="dm", obstacles=False, drones=8,
                  start="gate", seed=5)
    pos, _, gate = env.spawn(400)
    assert not track.arena.outside_xy(pos.numpy()).any()
    assert (gate == 0).any()                      # gate 0 itself still starts races, with a fitting draw
    ground = RaceEnv(track, load_profile(DEFAULT_PROFILE), num_envs=1, method="dm", obstacles=False, drones=8,
                     start="ground")
    with pytest.raises(ConfigError, match="8-drone start grid of the lemniscate track leaves its arena"):
        ground.spawn(4)
    four = RaceEnv(track, load_profile(DEFAULT_PROFILE), num_envs=1, method="dm", obstacles=False, drones=4,
                   start="ground")
    assert not track.arena.outside_xy(four.spawn(4)[0].numpy()).any()


def test_ground_start_grid_must_fit_the_arena():
    lem, cpx = load_track("lemniscate"), load_track("complex")
    for n in (2, 4, 6):
        pos, _ = ground_start_positions(lem, n)
        assert not lem.arena.outside_xy(pos).any()
    with pytest.raises(ConfigError, match=r"8 drones do not fit the lemniscate track's start grid: drone 7's slot "
                                          r"\(1.30, 1.90\) m lies outside the arena .* at most 6 drones"):
        ground_start_positions(lem, 8)
    pos, _ = ground_start_positions(cpx, 16)
    assert not cpx.arena.outside_xy(pos).any()


def test_placings_winners_and_pairwise():
    nan = float("nan")
    ft = np.array([[10.0, 9.0, nan, nan], [nan, nan, nan, nan], [8.0, 8.0, nan, 7.5]])
    gates = np.array([[18, 18, 12, 12], [5, 7, 7, 1], [18, 18, 3, 18]])
    pl = placings(ft, gates)
    assert pl.tolist() == [[2, 1, 3, 3], [3, 1, 1, 4], [2, 2, 4, 1]]
    assert winners(ft, pl).tolist() == [1, -1, 3]
    who = np.array([[0, 1, 2, 2], [0, 1, 2, 2], [0, 1, 2, 2]])   # player 2 entered twice
    wins, games = pairwise(pl, who, 3)
    assert games[0, 1] == 3 and games[2, 2] == 0                # a player does not meet itself
    assert wins[0, 1] == 0.5 and wins[1, 0] == 2.5              # 1 ahead twice, one shared place
    assert np.allclose(wins + wins.T, games)


def test_rating_recovers_known_strengths_and_is_order_free():
    rng = np.random.default_rng(0)
    true = np.array([1300.0, 1500.0, 1700.0, 1600.0])
    wins = np.zeros((4, 4))
    games = np.zeros((4, 4))
    for _ in range(4000):
        i, j = rng.choice(4, 2, replace=False)
        a_wins = rng.random() < expected_score(true[i], true[j])
        wins[i, j] += a_wins
        wins[j, i] += 1 - a_wins
        games[i, j] += 1
        games[j, i] += 1
    r = fit_ratings(wins, games, prior_games=0.0)
    assert np.abs((r - r.mean()) - (true - true.mean())).max() < 40
    perm = [2, 0, 3, 1]
    r2 = fit_ratings(wins[np.ix_(perm, perm)], games[np.ix_(perm, perm)], prior_games=0.0)
    assert np.allclose(r2, r[perm], atol=1e-6)
    # one player wins everything: finite with the prior, and the best
    w = np.array([[0, 10.0], [0, 0]])
    g = np.array([[0, 10.0], [10.0, 0]])
    r = fit_ratings(w, g)
    assert np.isfinite(r).all() and r[0] > r[1] + 300
    # even results: equal ratings at the anchor
    assert fit_ratings(np.full((2, 2), 5.0) * (1 - np.eye(2)), np.full((2, 2), 10.0) * (1 - np.eye(2))) == \
        pytest.approx([1500.0, 1500.0])


def test_c_kernel_takes_eight_drones_and_the_fallback_says_so():
    from cfrace.sim import ckernel
    from cfrace.sim.simulator import Simulator

    if not ckernel.available():
        pytest.skip("no C compiler")
    track, prof = load_track("lemniscate"), load_profile(DEFAULT_PROFILE)
    sims = [Simulator(track, prof, 2, 8, obstacles=False, backend=b) for b in ("c", "torch")]
    grid = torch.as_tensor(start_grid(track.spawn, track.gate, 8), dtype=torch.float32)
    pos = torch.stack([grid[:, 0], 4.0 + grid[:, 1], torch.full((8,), 1.0)], -1).expand(2, 8, 3)
    for s in sims:
        s.reset(torch.arange(2), pos)
    thrust = torch.full((2, 8), prof.mass * 9.81 * 1.05)
    rates = torch.randn(2, 8, 3, generator=torch.Generator().manual_seed(0)) * 0.5
    for _ in range(20):
        for s in sims:
            s.step(thrust, rates)
    assert sims[0].backend == "c"
    assert torch.allclose(sims[0].pos, sims[1].pos, atol=2e-3)
    with pytest.warns(RuntimeWarning, match="at most 16"):
        s = Simulator(track, prof, 1, 17, obstacles=False)
    assert s.backend == "torch"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Simulator(track, prof, 1, 16, obstacles=False)


def test_warm_start_from_an_exported_policy_acts_like_it():
    import types

    from cfrace.policy import OnnxPolicy
    from cfrace.paths import POLICIES_DIR
    from cfrace.rl.models import AgentModels
    from cfrace.rl.warmstart import warm_start

    path = POLICIES_DIR / "ours_lemniscate.onnx"
    pol = OnnxPolicy(path)
    m = AgentModels(42, 168, (128, 128), (256, 128), 0.27)
    info = warm_start(types.SimpleNamespace(agents=[m]), path, "race42")
    obs = (np.random.default_rng(0).normal(size=(64, 42)) * 2).astype(np.float32)
    with torch.no_grad():
        mine = m.actor(m.obs_norm(torch.from_numpy(obs))).mean.clamp(-1, 1).numpy()
    assert np.abs(mine - pol(obs)).max() < 1e-5
    assert info["init_env_steps"] == pol.meta["train_steps"]
    from cfrace.errors import ConfigError

    with pytest.raises(ConfigError, match="no critic"):
        warm_start(types.SimpleNamespace(agents=[m]), path, "race42", critic=True)


def test_race_entrants_cli(tmp_path, run_cli):
    out = tmp_path / "r.json"
    res = run_cli("race", "--track", "lemniscate", "--entrants", "ours,ds,ours", "--races", "2", "--laps", "1",
                  "--json", str(out), "--plot", str(tmp_path / "p"), "--opponent-rule", "ahead")
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert data["entrants"] == ["ours", "ds", "ours#2"] and data["opponent_rule"] == "ahead"
    assert len(data["finishing_order"]) == 2 and all(len(o) == 3 for o in data["finishing_order"])
    assert sum(data["policy_win_rate"].values()) + data["no_winner_rate"] == pytest.approx(1.0)
    assert {tuple(c["pair"]) for c in data["contacts_by_pair"]} == {("ours", "ds"), ("ours", "ours#2"), ("ds", "ours#2")}
    assert (tmp_path / "p" / "field_trajectories.png").stat().st_size > 10_000
    assert (tmp_path / "p" / "field_positions.png").stat().st_size > 10_000
    from cfrace.errors import ConfigError

    bad = run_cli("race", "--track", "lemniscate", "--entrants", "ours,,ds")
    assert isinstance(bad.exception, ConfigError) and "empty name" in str(bad.exception)
    both = run_cli("race", "--track", "lemniscate", "--entrants", "ours,ds", "--ego", "ours")
    assert isinstance(both.exception, ConfigError) and "not both" in str(both.exception)


def test_free_for_all_cli(tmp_path, run_cli):
    out = tmp_path / "t.json"
    res = run_cli("tournament", "ours", "ds", "ss", "--track", "lemniscate", "--field", "3", "--races", "2",
                  "--laps", "1", "--json", str(out), "--heatmap", str(tmp_path / "rating.png"))
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert data["heats"] == [["ours", "ds", "ss"]] and set(data["rating"]) == {"ours", "ds", "ss"}
    assert all(math.isfinite(v) for v in data["rating"].values())
    assert (tmp_path / "rating.png").exists()
    from cfrace.errors import ConfigError

    few = run_cli("tournament", "ours", "ds", "--track", "lemniscate", "--field", "3")
    assert isinstance(few.exception, ConfigError) and "at least 3 policies" in str(few.exception)


def test_shared_runner_trains_one_model_for_every_drone(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from toy_env import ToyRaceEnv

    from cfrace.rl.config import parse_overrides, preset
    from cfrace.rl.runner import Runner

    assert parse_overrides(["shared=true"]) == (("shared", True),)
    env = ToyRaceEnv(32, 2, episode_steps=10, seed=0)   # the toy's critic knows two drones
    cfg = preset("cpu", multi_agent=True, num_envs=32, rollout=8, actor_hidden=(16,), critic_hidden=(16,),
                 shared=True)
    runner = Runner(env, cfg, seed=0)
    assert len(runner.agents) == 1 and all(runner.model(a) is runner.agents[0] for a in range(2))
    before = runner.agents[0].actor.mean_net[0].weight.clone()
    m = runner.iterate()
    assert not torch.equal(before, runner.agents[0].actor.mean_net[0].weight)
    assert all(f"reward_agent{a}" in m for a in range(2)) and "surrogate_agent0" in m and "surrogate_agent1" not in m
    # one update on every drone's alive samples: the normaliser saw all of them
    assert runner.agents[0].obs_norm.count >= 32 * 2 + 32 * 8
    state = runner.state_dict()
    again = Runner(ToyRaceEnv(32, 2, episode_steps=10, seed=0), cfg, seed=0)
    again.load_state_dict(state)
    assert torch.equal(again.agents[0].actor.mean_net[0].weight, runner.agents[0].actor.mean_net[0].weight)


def test_radio_budget_from_bitcraze_figures():
    from cfrace.errors import ConfigError
    from cfrace.flight.link.radio import check_radios, max_drones_per_radio, parse_radio_uri

    assert max_drones_per_radio(100.0) == 4 and max_drones_per_radio(50.0) == 8
    r = parse_radio_uri("radio://0/80/2M/e7e7e7e7e1")
    assert (r.device, r.channel, r.datarate, r.address) == (0, 80, "2M", "E7E7E7E7E1")
    assert parse_radio_uri("udp://127.0.0.1:19850") is None
    four = [f"radio://0/80/2M/E7E7E7E7E{i}" for i in range(1, 5)]
    assert len(check_radios(four + ["udp://127.0.0.1:1"])[0]) == 4
    with pytest.raises(ConfigError, match="carries 5 drones.*at most 4"):
        check_radios(four + ["radio://0/80/2M/E7E7E7E7E5"])
    assert len(check_radios(four + ["radio://1/80/2M/E7E7E7E7E5"])) == 2     # a second radio
    with pytest.raises(ConfigError, match="one channel"):
        check_radios(["radio://0/80/2M/E7E7E7E7E1", "radio://0/90/2M/E7E7E7E7E2"])
    with pytest.raises(ConfigError, match="one address"):
        check_radios(["radio://0/80/2M/E7E7E7E7E1", "radio://0/80/2M/e7e7e7e7e1?safelink=0"])
    with pytest.raises(ConfigError, match="the same drone .* on two radios"):     # one drone, two radios
        check_radios(["radio://0/80/2M/E7E7E7E7E1", "radio://1/80/2M/E7E7E7E7E1"])
    with pytest.raises(ConfigError, match="not a Crazyradio URI"):
        parse_radio_uri("radio://0/200/2M")
