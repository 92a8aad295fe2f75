"""The lab-loop model (cfrace.loopmodel) that training and the dry-run's simulated mocap share: its
rules, the env's reading of frames through the flight estimator's rules (checked against the
estimator itself), the drone ranges drawn from calibration/, and bad input to the new options."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from cfrace.drone import GRAVITY, load_profile
from cfrace.errors import ConfigError
from cfrace.flight.mocap.estimation import PoseEstimator
from cfrace.flight.mocap.base import MocapFrame, Pose
from cfrace.loopmodel import (IDLE_THRUST_COUNTS, predict_commanded, MOCAP_PERIOD_S, DroneRanges, LoopRanges, drone_ranges, frame_age,
                              interpolate_pose, perturb_pose, rotate_body)
from cfrace.track import load_track

CFRACE = Path(sys.executable).with_name("cfrace")


def _unit(q):
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def test_the_rules_agree_on_numpy_and_torch_and_keep_unit_quaternions():
    rng = np.random.default_rng(0)
    pa, pb = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    qa, qb = _unit(rng.normal(size=(5, 4))), _unit(rng.normal(size=(5, 4)))
    w = rng.random((5, 1))
    p_np, q_np = interpolate_pose(pa, qa, pb, qb, w)
    p_t, q_t = interpolate_pose(*(torch.tensor(x) for x in (pa, qa, pb, qb, w)))
    assert np.allclose(p_np, p_t.numpy()) and np.allclose(q_np, q_t.numpy())
    assert np.allclose(np.linalg.norm(q_np, axis=-1), 1.0)
    # the ends are the samples themselves (qb up to its sign: the blend takes qa's hemisphere)
    p0, q0 = interpolate_pose(pa, qa, pb, qb, 0.0)
    p1, q1 = interpolate_pose(pa, qa, pb, qb, 1.0)
    assert np.allclose(p0, pa) and np.allclose(q0, qa) and np.allclose(p1, pb)
    assert np.allclose(np.abs((q1 * qb).sum(-1)), 1.0)
    pos, quat = perturb_pose(pa, qa, rng.normal(size=(5, 3)), 0.002, rng.normal(size=(5, 3)), 0.01)
    assert np.allclose(np.linalg.norm(quat, axis=-1), 1.0)
    angle = 2 * np.arccos(np.clip(np.abs((quat * qa).sum(-1)), 0, 1))
    assert (angle < 0.1).all() and (angle > 0).all()
    assert perturb_pose(pa, qa, np.zeros((5, 3)), 0.002)[1] is qa       # no attitude noise: untouched
    ages = frame_age(np.full(1000, 0.001), 0.002, rng.random(1000))
    assert ages.min() >= 0.0 and ages.max() <= 0.003


def test_rotate_body_is_the_estimators_prediction():
    from cfrace.flight.mocap.estimation import _rotate_body
    rng = np.random.default_rng(1)
    for _ in range(20):
        q, omega, h = _unit(rng.normal(size=4)), rng.normal(size=3) * 5, float(rng.random() * 0.03)
        assert np.allclose(rotate_body(q, omega, h), _rotate_body(tuple(q), tuple(omega), h), atol=1e-12)
    assert np.allclose(rotate_body(q, np.zeros(3), 0.01), q)


def test_predict_commanded_is_the_estimators_prediction():
    from cfrace.flight.mocap.estimation import _predict_commanded
    rng = np.random.default_rng(2)
    for _ in range(20):
        p, v, q = rng.normal(size=3), rng.normal(size=3) * 3, _unit(rng.normal(size=4))
        acc, h, lag = float(rng.random() * 20), float(rng.random() * 0.03), 0.005
        ref = _predict_commanded(tuple(p), tuple(v), tuple(q), acc, h, lag)
        for a, b in zip(predict_commanded(p, v, q, acc, h, lag), ref):
            assert np.allclose(a, b, atol=1e-12)
    # hover thrust, level: nothing moves; no thrust: a free fall of g h^2 / 2
    level = np.array([1.0, 0.0, 0.0, 0.0])
    pos, vel = predict_commanded(np.zeros(3), np.zeros(3), level, GRAVITY, 0.02, 0.005)
    assert np.allclose(pos, 0.0) and np.allclose(vel, 0.0)
    pos, vel = predict_commanded(np.zeros(3), np.zeros(3), level, 0.0, 0.02, 0.0)
    assert np.isclose(pos[2], -0.5 * GRAVITY * 0.02 ** 2) and np.isclose(vel[2], -GRAVITY * 0.02)


def test_the_commanded_prediction_brings_a_late_pose_closer_to_the_drone_than_the_velocity_alone():
    """Drones flown in the training simulator, each on its own steady command, their poses 20 ms
    late: told the command it sent, the estimator puts them nearer where they are now than the
    velocity alone does (the rest is drag and the motors' lag)."""
    from cfrace.env.race_env import RaceEnv
    latency = 0.020
    loop = LoopRanges(latency_s=(latency, latency), jitter_s=0.0, noise_m=(0.0, 0.0), att_noise_rad=(0.0, 0.0),
                      drop=(0.0, 0.0), late=0.0, comp=1.0)
    env = RaceEnv(load_track("lemniscate"), load_profile("cf2x_paper"), num_envs=64, method="ds", obstacles=False,
                  seed=3, loop=loop)
    env.reset()
    gen = torch.Generator().manual_seed(1)
    err = {(cmd, what): [] for cmd in (True, False) for what in ("pos", "vel")}
    a = torch.rand(64, 1, 4, generator=gen) * 0.4 - 0.2
    a[..., 0] += 0.1
    for _ in range(8):
        env.step(a)
        draw = env._rand
        for cmd in (True, False):
            env.lp_fresh[:] = not cmd            # no command known: the velocity and measured rates
            env._rand = lambda *shape: torch.full(shape, 0.5)
            pos, vel, quat = env._loop_observe()
            err[cmd, "pos"].append(torch.linalg.vector_norm(pos - env.sim.pos, dim=-1).mean().item())
            err[cmd, "vel"].append(torch.linalg.vector_norm(vel - env.sim.vel, dim=-1).mean().item())
        env.lp_fresh[:], env._rand = False, draw
    for what in ("pos", "vel"):
        assert np.mean(err[True, what]) < 0.5 * np.mean(err[False, what]), (what, err)


@pytest.mark.parametrize("comp, drop", [(0.0, 0), (1.0, 0), (1.0, 1), (0.0, 2)])
def test_the_env_reads_frames_as_the_flight_estimator_does(comp, drop):
    """Training's delayed observation against the flight stack's PoseEstimator fed the same frames:
    the frame of this tick and the two before it (pose age 17 ms, between two 100 Hz samples), with
    latency compensation on or off, this tick's frame (drop 1) or the one before (drop 2) lost."""
    from cfrace.env.race_env import RaceEnv
    latency = 0.017
    loop = LoopRanges(latency_s=(latency, latency), jitter_s=0.0, noise_m=(0.0, 0.0), att_noise_rad=(0.0, 0.0),
                      drop=(0.0, 0.0), late=0.0, comp=comp)
    env = RaceEnv(load_track("lemniscate"), load_profile("cf2x_paper"), num_envs=3, method="ds", obstacles=False,
                  seed=4, loop=loop)
    env.reset()
    gen = torch.Generator().manual_seed(0)
    for _ in range(6):      # fly a little: the drones move and turn
        env.step(torch.rand(3, 1, 4, generator=gen) * 2 - 1)
    hp, hq = env.hist_pos.double().numpy(), env.hist_quat.double().numpy()      # (E, A, K, .) newest first
    drops = {0: (False, False), 1: (True, False), 2: (False, True)}[drop]
    env.lp_drop[:] = 0.5     # draws below it lose the frame: 0 loses it, 1 keeps it
    draws = iter([torch.full((3, 1), 0.5)] + [torch.full((3, 1), 0.0 if d else 1.0) for d in drops])
    env._rand = lambda *shape: next(draws)     # _loop_observe's draws: jitter, this frame lost, the one before
    pos, vel, quat = (x.double().numpy() for x in env._loop_observe())
    k, w = divmod(latency / MOCAP_PERIOD_S, 1.0)
    for e in range(3):
        est = PoseEstimator(["cf1"], alpha=1.0, lead_s=latency if comp else 0.0)
        est.command("cf1", float(env.cmd_acc[e, 0]))   # the step's command
        # the frames of the ticks 2, 1, 0 before now (age latency), oldest first; a lost one is absent
        for tick in (2, 1, 0):
            i = int(k) + tick
            p, q = interpolate_pose(hp[e, 0, i], hq[e, 0, i], hp[e, 0, i + 1], hq[e, 0, i + 1], w)
            lost = (tick == 0 and drops[0]) or (tick == 1 and drops[1])
            t = -tick * MOCAP_PERIOD_S - latency
            poses = {} if lost else {"cf1": Pose(pos=p, quat=q)}
            got = est.update(MocapFrame(t=t, poses=poses, seq=3 - tick), now=-tick * MOCAP_PERIOD_S)
        ref = got["cf1"]
        assert np.allclose(pos[e, 0], ref.pos, atol=2e-5), (pos[e, 0], ref.pos)
        assert np.allclose(vel[e, 0], ref.vel, atol=5e-3), (vel[e, 0], ref.vel)
        assert np.allclose(np.abs((quat[e, 0] * ref.quat).sum()), 1.0, atol=1e-5)


def test_training_through_the_loop_draws_what_the_ranges_say_and_resumes_exactly():
    from cfrace.env.race_env import RaceEnv
    prof = load_profile("cf2x_paper")
    dr = drone_ranges(prof, [load_profile("cf21bl")])
    env = RaceEnv(load_track("lemniscate"), prof, num_envs=64, method="ours", obstacles=False, seed=2,
                  loop=LoopRanges(), drone=dr)
    env.reset()
    lo, hi = LoopRanges().latency_s
    assert env.flight_obs and (env.lp_latency >= lo).all() and (env.lp_latency <= hi).all()
    # 128 draws each: within 0.2 of the share asked is more than 4 standard deviations
    assert abs(env.lp_late.float().mean() - LoopRanges().late) < 0.2
    assert abs(env.lp_comp.float().mean() - LoopRanges().comp) < 0.2
    tau = env.sim.scales["tau_m"]
    lo, hi = min(dr.tau_m) * dr.tau_jitter[0], max(dr.tau_m) * dr.tau_jitter[1]
    assert (tau >= lo - 1e-6).all() and (tau <= hi + 1e-6).all()
    brushless = (tau > 3.0 * dr.tau_jitter[1]).float().mean()     # drawn as cf21bl (tau 4 x), not a mix
    assert 0.25 < brushless < 0.55, brushless                      # (1 - blend) / 2 = 0.4 expected
    floor_w = env.dr_floor / prof.weight
    assert (floor_w <= max(dr.thrust_floor_w) * dr.floor_jitter[1] + 1e-6).all() and (floor_w > 0.15).any()
    gen = torch.Generator().manual_seed(0)
    acts = [torch.rand(64, 2, 4, generator=gen) * 2 - 1 for _ in range(8)]
    for a in acts[:4]:
        env.step(a)
    state = env.state_dict()
    first = [env.step(a).obs for a in acts[4:]]
    env.load_state_dict(state)
    again = [env.step(a).obs for a in acts[4:]]
    assert all(torch.equal(x, y) for x, y in zip(first, again))
    assert all(torch.isfinite(x).all() for x in first)


def test_drone_ranges_span_the_profiles_in_calibration():
    paper, bl = load_profile("cf2x_paper"), load_profile("cf21bl")
    dr = drone_ranges(paper, [bl])
    assert dr.profiles == ("cf2x_paper", "cf21bl")
    assert dr.tau_m == (1.0, pytest.approx(bl.tau_m / paper.tau_m, abs=1e-3))
    for p, cap in zip((paper, bl), dr.thrust_cap_w):
        assert cap == pytest.approx(p.max_collective_thrust / p.weight, abs=1e-3)
    idle = bl.thrust_curve.to_newtons(IDLE_THRUST_COUNTS["cf21bl"]) / bl.weight
    assert dr.thrust_floor_w == (0.0, pytest.approx(idle, abs=1e-3))
    assert dr.pid[0] == 1.0 and dr.pid[1] != 1.0
    assert DroneRanges.from_meta(dr.to_meta()) == dr
    assert drone_ranges(paper, []).tau_m == (1.0,)       # only itself: its own neighbourhood
    with pytest.raises(ConfigError, match="one value per profile"):
        DroneRanges(profiles=("a", "b"), tau_m=(1.0,), thrust_cap_w=(2.0, 2.0), thrust_floor_w=(0, 0), pid=(1, 1))


@pytest.mark.parametrize("given, words", [(dict(latency_s=(-0.001, 0.02)), ["latency", "within"]),
                                          (dict(noise_m=(0.003, 0.001)), ["upside down"]),
                                          (dict(late=1.5), ["late setpoints", "probability"])])
def test_bad_ranges_are_one_line(given, words):
    with pytest.raises(ConfigError) as exc:
        LoopRanges(**given)
    assert all(w in str(exc.value) for w in words) and "\n" not in str(exc.value)


def test_the_train_options_refuse_bad_input_in_one_line(tmp_path):
    env = dict(os.environ, COLUMNS="200")
    cases = [(["--lab-loop", "--loop-latency-ms", "-5,30"], "--loop-latency-ms"),
             (["--lab-loop", "--loop-noise-mm", "3,1"], "upside down"),
             (["--span-profiles", "cf99"], "--span-profiles"),
             (["--loop-latency-ms", "0,20"], "only with --lab-loop")]
    for extra, word in cases:
        r = subprocess.run([str(CFRACE), "train", "--method", "ds", "--track", "lemniscate", "--steps", "10",
                            "--out", str(tmp_path / "run"), *extra], capture_output=True, text=True, env=env,
                           timeout=240, cwd=tmp_path)
        assert r.returncode == 2 and "Traceback" not in r.stderr and r.stderr.count("\n") == 1, r.stderr
        assert word in r.stderr, r.stderr
        assert not (tmp_path / "run").exists()


def test_a_run_through_the_loop_records_its_ranges_in_the_policy(tmp_path):
    from cfrace.export import export_checkpoint
    from cfrace.policy import OnnxPolicy
    from cfrace.rl.train import TrainConfig, train
    small = (("actor_hidden", (16, 16)), ("critic_hidden", (16,)))
    cfg = TrainConfig("ds", "lemniscate", num_envs=8, steps=8 * 24, device="cpu", threads=1, seed=3,
                      out=str(tmp_path / "run"), overrides=small, loop=LoopRanges().to_meta(),
                      span_profiles=("cf21bl",))
    res = train(cfg)
    export_checkpoint(res.checkpoint, tmp_path / "p.onnx")
    meta = OnnxPolicy(tmp_path / "p.onnx").meta
    assert LoopRanges.from_meta(meta["loop"]) == LoopRanges() and meta["flight_obs"] is True
    assert DroneRanges.from_meta(meta["drone_ranges"]).profiles == ("cf2x_paper", "cf21bl")
    assert math.isclose(meta["drone_ranges"]["tau_m"][1], 4.0)


def test_the_robustness_grid_flies_through_the_lockstep_stack_and_writes_its_table_and_figure(tmp_path):
    """`cfrace sim robustness --quick`: every cell flown (alone for each policy, one duel), the rows
    add up to the cells, and the three files exist; a bad option is one line and exit 2."""
    import json
    run = lambda *a: subprocess.run([sys.executable, "-m", "cfrace", "sim", "robustness", *a],
                                    capture_output=True, text=True, timeout=300)
    r = run("--quick", "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr[-2000:]
    got = json.loads((tmp_path / "robustness.json").read_text())
    assert (tmp_path / "robustness.png").stat().st_size > 1000 and (tmp_path / "robustness.md").exists()
    cells = got["cells"]
    assert {(c["latency_ms"], c["profile"]) for c in cells} == {(a, p) for a in (0.0, 20.0) for p in ("cf2x_paper", "cf21bl")}
    alone = [row for row in got["rows"] if row["kind"] == "alone"]
    assert len(alone) == 2 * len(cells)                      # ours and ds, one seed, per cell
    assert all(0 <= row["laps"] <= 1 for row in alone)
    assert all((row["end"] == "finished") == row["finished"] for row in alone)
    for bad, word in ((["--quick", "--latencies-ms", "20,-5"], "--latencies-ms"), (["--profiles", "cf9"], "--profiles")):
        r = run(*bad, "--out", str(tmp_path / "bad"))
        assert r.returncode == 2 and word in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert not (tmp_path / "bad" / "robustness.json").exists()


def test_the_grid_flies_each_profile_at_its_firmwares_idle_thrust_when_asked():
    """--firmware-idle: the Brushless boots with powerDist.idleThrust 7000, a brushed drone with 0;
    without it the simulator's default (None reaches the dry-run); the table names the idle."""
    from cfrace.evaluate.robustness import Grid, _idle, _profile_label
    on, off = Grid(firmware_idle=True), Grid()
    assert (_idle(on, "cf21bl"), _idle(on, "cf2x_paper"), _idle(off, "cf21bl")) == (7000, 0, None)
    assert _profile_label({"firmware_idle": True}, "cf21bl") == "cf21bl (idle 7000)"
    assert _profile_label({"firmware_idle": True}, "cf2x_paper") == "cf2x_paper"
    assert _profile_label({}, "cf21bl") == "cf21bl"
