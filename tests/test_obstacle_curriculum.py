"""The obstacle curriculum (`cfrace train --obstacle-curriculum ITERS`): the obstacles' geometry at
each iteration, the simulator's contacts with grown obstacles, the metadata, and the warm start from
a policy of the track without obstacles (no world position in its observation)."""

from __future__ import annotations

import csv
import math
import sys
import types

import numpy as np
import pytest
import torch

from cfrace.drone import load_profile
from cfrace.env.race_env import RaceEnv
from cfrace.errors import ConfigError
from cfrace.export import export_checkpoint
from cfrace.policy import OnnxPolicy
from cfrace.rl.curves import read_curve, reduce_metrics
from cfrace.rl.models import AgentModels
from cfrace.rl.train import FORMAT, TrainConfig, make_env, train
from cfrace.rl.warmstart import warm_start
from cfrace.sim import ckernel
from cfrace.sim.simulator import Simulator
from cfrace.track import load_track, obstacle_scale

pytestmark = pytest.mark.usefixtures("one_torch_thread")

LEM = load_track("lemniscate")
CPX = load_track("complex")
PROFILE = load_profile("cf2x_paper")
BACKENDS = ["torch"] + (["c"] if ckernel.available() else [])


def test_schedule_grows_linearly_to_full_size():
    assert [obstacle_scale(i, 4) for i in (0, 1, 2, 4, 5, 100)] == [0.0, 0.25, 0.5, 1.0, 1.0, 1.0]
    assert obstacle_scale(0, 0) == 1.0 and obstacle_scale(7, 0) == 1.0   # no curriculum: full size


def test_lemniscate_obstacles_grow_from_where_they_join():
    """The lemniscate's two obstacles overlap (one barrier): each grows from its end at the joint,
    hand-computed from tracks/lemniscate.yaml; full size is the track as defined."""
    c1, h1, y1 = LEM.obstacle_boxes()
    for got, want in zip(LEM.obstacle_boxes(1.0), (c1, h1, y1)):
        assert np.array_equal(got, want)
    anchors = LEM.obstacle_anchors()
    assert np.allclose(anchors[0], [0.0, 7.0])   # obstacle 0 (y 7.0 .. 8.3): its lower end, at the wall
    yaw = -0.78                                   # obstacle 1: 3 m wall, its upper end, at obstacle 0
    assert np.allclose(anchors[1], [-1.0 - 1.5 * math.sin(yaw), 6.0 + 1.5 * math.cos(yaw)])
    c, h, y = LEM.obstacle_boxes(0.5)
    assert np.allclose(c[0], [0.0, 7.325, 4.0]) and np.allclose(h[0], [0.05, 0.325, 4.0])
    assert np.allclose(c[1, :2], (anchors[1] + [-1.0, 6.0]) / 2) and np.allclose(h[1], [0.05, 0.75, 4.0])
    assert np.array_equal(y, y1)
    c0, h0, _ = LEM.obstacle_boxes(0.0)
    assert np.allclose(c0[:, :2], anchors) and np.allclose(h0[:, :2], 0.0) and np.allclose(h0[:, 2], 4.0)
    with pytest.raises(ValueError, match="in \\[0, 1\\]"):
        LEM.obstacle_boxes(1.5)


def test_separate_obstacles_grow_from_their_centres():
    c, h, _ = CPX.obstacle_boxes()
    c2, h2, _ = CPX.obstacle_boxes(0.25)
    assert np.allclose(CPX.obstacle_anchors(), c[:, :2])
    assert np.allclose(c2, c) and np.allclose(h2[:, :2], h[:, :2] / 4) and np.allclose(h2[:, 2], h[:, 2])


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_simulator_collides_with_the_grown_obstacles(backend):
    """A drone flying at obstacle 0's upper part (y 8.1) touches it at full size, not at half size
    (it then ends at y 7.65); the same simulator, rescaled in place, touches it again."""
    sim = Simulator(LEM, PROFILE, 1, 1, obstacles=True, backend=backend)

    def touches() -> bool:
        sim.reset(torch.tensor([0]), torch.tensor([[[0.4, 8.1, 1.0]]]))
        sim.state.vel[0, 0] = torch.tensor([-2.0, 0.0, 0.0])
        hover = torch.full((1, 1), PROFILE.weight)
        return any(bool(sim.step(hover, torch.zeros(1, 1, 3)).contact[0, 0]) for _ in range(20))

    assert touches()
    sim.set_obstacle_scale(0.5)
    assert sim.obstacle_scale == 0.5 and not touches()
    sim.set_obstacle_scale(1.0)
    assert touches()


def _cfg(tmp_path, **kw):
    base = dict(method="ss", track="lemniscate", obstacles=True, num_envs=8, steps=8 * 24 * 3, device="cpu",
                threads=1, seed=3, out=str(tmp_path / "run"), obstacle_curriculum=4, episode_s=0.3,
                overrides=(("rollout", 24), ("actor_hidden", (16, 16)), ("critic_hidden", (16,))))
    base.update(kw)
    return TrainConfig(**base)


def test_training_follows_the_schedule_and_records_it(tmp_path):
    """Three iterations on the real env: the env's obstacles at 0, 1/4, 2/4 of their size, logged per
    iteration, and the curriculum in the checkpoint's and the exported policy's metadata."""
    seen = []

    def factory(cfg, device, num_envs):
        env, meta = make_env(cfg, device, num_envs)
        step = env.step
        env.step = lambda a: (seen.append(float(env.sim.geometry.obstacles.half[0, 1])), step(a))[1]
        return env, meta

    res = train(_cfg(tmp_path), env_factory=factory)
    with open(res.out / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["stat_obstacle_scale"]) for r in rows] == [0.0, 0.25, 0.5]   # 0.3-s races: each iteration ends some
    half = LEM.obstacles[0].size[1] / 2
    assert np.allclose(sorted(set(seen)), [0.0, 0.25 * half, 0.5 * half])
    curve = reduce_metrics(res.out / "metrics.csv", tmp_path / "curve.csv")   # the kept curve keeps the size
    assert [float(x) for x in read_curve(curve)["stat_obstacle_scale"]] == [0.0, 0.25, 0.5]
    policy = tmp_path / "p.onnx"
    _, meta, _ = export_checkpoint(res.checkpoint, policy)
    assert meta["obstacle_curriculum"] == 4 == OnnxPolicy(policy).meta["obstacle_curriculum"]


def test_curriculum_without_obstacles_is_one_line_error(tmp_path, monkeypatch, capsys):
    with pytest.raises(ConfigError, match="needs --obstacles"):
        train(_cfg(tmp_path, obstacles=False))
    from cfrace.cli.main import main

    monkeypatch.setattr(sys, "argv", ["cfrace", "train", "--method", "ss", "--track", "lemniscate", "--steps", "10",
                                      "--envs", "8", "--obstacle-curriculum", "5", "--out", str(tmp_path / "x")])
    with pytest.raises(SystemExit) as exc:
        main()
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(err) == 1 and "needs --obstacles" in err[0], err


def test_warm_start_from_a_policy_without_world_position(tmp_path):
    """A solo36 policy (track without obstacles) into the 39-D obstacle layout: the world position
    has zero weight (the copy acts exactly like its source wherever it is), its normaliser the
    arena's centre and uniform variance; the critic likewise; the reverse is refused."""
    torch.manual_seed(0)
    src = AgentModels(36, 36, (32, 32), (32,), 0.5)
    src.obs_norm.update(torch.randn(500, 36) * 3 + 1)
    src.critic_norm.update(torch.randn(500, 36) * 2)
    torch.save({"format": FORMAT, "meta": {"obs_layout": "solo36"},
                "runner": {"agents": [src.state_dict()], "total_reward": torch.tensor([1.0]), "env_steps": 5}},
               tmp_path / "checkpoint.pt")
    env = RaceEnv(LEM, PROFILE, num_envs=2, method="ss", obstacles=True)
    dst = AgentModels(39, 39, (32, 32), (32,), 1.0)
    info = warm_start(types.SimpleNamespace(agents=[dst], env=env), tmp_path, "solo39_obstacles", critic=True)
    assert info["init_layout"] == "solo36"
    x = torch.randn(64, 39) * 3
    with torch.no_grad():
        assert torch.allclose(dst.actor(dst.obs_norm(x)).mean, src.actor(src.obs_norm(x[:, 3:])).mean, atol=1e-6)
        assert torch.allclose(dst.critic(dst.critic_norm(x)), src.critic(src.critic_norm(x[:, 3:])), atol=1e-5)
    a = LEM.arena
    assert torch.allclose(dst.obs_norm.mean[:3], torch.tensor([sum(a.x) / 2, sum(a.y) / 2, a.z_max / 2],
                                                              dtype=torch.float64))
    assert torch.allclose(dst.obs_norm.var[:3], torch.tensor([(a.x[1] - a.x[0]) ** 2 / 12, (a.y[1] - a.y[0]) ** 2 / 12,
                                                              a.z_max ** 2 / 12], dtype=torch.float64))
    torch.save({"format": FORMAT, "meta": {"obs_layout": "solo39_obstacles"},
                "runner": {"agents": [dst.state_dict()], "total_reward": torch.tensor([1.0]), "env_steps": 5}},
               tmp_path / "obst.pt")
    with pytest.raises(ConfigError, match="does not fit into solo36"):
        warm_start(types.SimpleNamespace(agents=[AgentModels(36, 36, (32, 32), (32,), 1.0)]), tmp_path / "obst.pt",
                   "solo36")
