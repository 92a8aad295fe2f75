"""Pose estimator: velocity, attitude, occlusions, staleness, outliers, NaN, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cfrace.flight.mocap.estimation import PREDICTIONS, PoseEstimator, estimates_to_msg
from cfrace.rotations import quat_to_rot
from cfrace.flight.mocap.sources import MocapFrame, Pose

Q0 = np.array([1.0, 0.0, 0.0, 0.0])
DT = 0.01


def yaw_quat(yaw: float) -> np.ndarray:
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def frame(k: int, poses: dict, dt: float = DT) -> MocapFrame:
    return MocapFrame(t=500.0 + k * dt, poses={b: Pose(np.asarray(p, float), np.asarray(q, float))
                                              for b, (p, q) in poses.items()}, seq=k + 1)


def test_constant_velocity_and_attitude():
    v = np.array([3.0, -1.5, 0.4])
    est = PoseEstimator(["cf1"], alpha=0.3)
    for k in range(30):
        e = est.update(frame(k, {"cf1": (v * k * DT, 2.0 * yaw_quat(0.5))}), now=k * DT)["cf1"]
    np.testing.assert_allclose(e.vel, v, atol=1e-9)
    np.testing.assert_allclose(e.pos, v * 29 * DT, atol=1e-12)
    assert e.valid and e.age_s == 0.0 and e.t == pytest.approx(500.29)
    np.testing.assert_allclose(np.linalg.norm(e.quat), 1.0)           # normalised
    np.testing.assert_allclose(e.rot, [[math.cos(0.5), -math.sin(0.5), 0],
                                       [math.sin(0.5), math.cos(0.5), 0], [0, 0, 1]], atol=1e-12)
    assert est.counters["cf1"] == {"frames": 30, "occluded": 0, "outliers": 0, "invalid": 0,
                                   "stale": 0, "reacquired": 0}


def test_rotation_matrix_maps_body_axes():
    # 90 deg about x: body y -> world z
    q = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0])
    np.testing.assert_allclose(quat_to_rot(q) @ [0, 1, 0], [0, 0, 1], atol=1e-12)
    r = quat_to_rot(np.array([0.3, -0.5, 0.7, 0.1]) / np.linalg.norm([0.3, -0.5, 0.7, 0.1]))
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_velocity_low_pass_reduces_noise():
    rng = np.random.default_rng(0)
    v = np.array([2.0, 0.0, 0.0])
    errs = {}
    for alpha in (1.0, 0.2):
        est = PoseEstimator(["cf1"], alpha=alpha)
        out = []
        for k in range(600):
            p = v * k * DT + rng.normal(0, 0.001, 3)
            out.append(est.update(frame(k, {"cf1": (p, Q0)}), k * DT)["cf1"].vel)
        errs[alpha] = np.std(np.array(out[100:]) - v)
    assert errs[0.2] < 0.5 * errs[1.0]


def test_occlusion_gap_prediction_and_staleness():
    v = np.array([1.0, 0.0, 0.0])
    est = PoseEstimator(["cf1", "cf2"], stale_after_s=0.1)
    for k in range(10):
        est.update(frame(k, {"cf1": (v * k * DT, Q0), "cf2": ([0, 0, 1], Q0)}), k * DT)
    ages, valid = [], []
    for k in range(10, 40):                     # cf1 occluded for 0.3 s
        e = est.update(frame(k, {"cf2": ([0, 0, 1], Q0)}), k * DT)
        ages.append(e["cf1"].age_s)
        valid.append(e["cf1"].valid)
        if k == 15:                              # short gap: predicted forward with its velocity
            np.testing.assert_allclose(e["cf1"].pos, v * 15 * DT, atol=1e-9)
        assert e["cf2"].valid
    assert all(b > a for a, b in zip(ages, ages[1:]))
    assert ages[-1] == pytest.approx(0.30)
    assert valid[:10] == [True] * 10 and not any(valid[11:])      # stale after 0.1 s
    held = est.update(None, 0.5)["cf1"]
    np.testing.assert_allclose(held.pos, v * (9 * DT + 0.1), atol=1e-9)   # prediction capped
    c = est.counters["cf1"]
    assert c["occluded"] == 30 and c["stale"] == 21   # 20 ticks in the gap + the held one
    e = est.update(frame(40, {"cf1": (v * 40 * DT, Q0)}), 40 * DT)["cf1"]   # seen again
    assert e.valid and e.age_s == 0.0
    np.testing.assert_allclose(e.vel, v, atol=1e-9)


def test_outlier_jump_rejected_and_counted():
    v = np.array([0.0, 2.0, 0.0])
    est = PoseEstimator(["cf1"], max_jump_m=0.3)
    for k in range(40):
        p = v * k * DT
        if k == 20:
            p = p + np.array([0.8, 0.0, 0.0])   # a mocap glitch (mirrored marker solution)
        e = est.update(frame(k, {"cf1": (p, Q0)}), k * DT)["cf1"]
        if k == 20:
            np.testing.assert_allclose(e.pos, v * 19 * DT + v * DT, atol=1e-9)   # predicted, not the glitch
            assert e.valid
    assert est.counters["cf1"]["outliers"] == 1
    np.testing.assert_allclose(e.vel, v, atol=1e-9)
    # 30 m/s in one frame is beyond max_speed even if below max_jump_m: allowed 0.3 m per 10 ms
    est2 = PoseEstimator(["cf1"], max_speed_mps=20.0, max_jump_m=0.05)
    est2.update(frame(0, {"cf1": ([0, 0, 1], Q0)}), 0.0)
    est2.update(frame(1, {"cf1": ([0.3, 0, 1], Q0)}), DT)
    assert est2.counters["cf1"]["outliers"] == 1


def test_consistent_outliers_reacquire_the_track():
    est = PoseEstimator(["cf1"], reacquire_after=5)
    est.update(frame(0, {"cf1": ([5.0, 5.0, 5.0], Q0)}), 0.0)      # first pose was a ghost
    for k in range(1, 10):
        e = est.update(frame(k, {"cf1": ([0.0, 0.01 * k, 1.0], Q0)}), k * DT)["cf1"]
    c = est.counters["cf1"]
    assert c["outliers"] == 5 and c["reacquired"] == 1
    np.testing.assert_allclose(e.pos, [0, 0.09, 1.0], atol=1e-12)
    np.testing.assert_allclose(e.vel, [0, 1.0, 0], atol=1e-9)


@pytest.mark.parametrize("bad", [([np.nan, 0, 1], Q0), ([0, 0, 1], [np.nan, 0, 0, 0]),
                                 ([np.inf, 0, 1], Q0), ([0, 0, 1], [0, 0, 0, 0])])
def test_nan_and_degenerate_poses_rejected(bad):
    est = PoseEstimator(["cf1"])
    est.update(frame(0, {"cf1": ([0, 0, 1], Q0)}), 0.0)
    e = est.update(frame(1, {"cf1": bad}), DT)["cf1"]
    assert np.isfinite(e.pos).all() and np.isfinite(e.vel).all() and np.isfinite(e.rot).all()
    assert est.counters["cf1"]["invalid"] == 1 and e.age_s == pytest.approx(DT)
    first = PoseEstimator(["cf1"])                        # a NaN as the very first pose
    e = first.update(frame(0, {"cf1": bad}), 0.0)["cf1"]
    assert not e.valid and first.counters["cf1"]["invalid"] == 1


def test_unseen_body_is_invalid_and_repeated_frames_ignored():
    est = PoseEstimator(["cf1", "ghost"])
    f = frame(0, {"cf1": ([0, 0, 1], Q0)})
    e = est.update(f, 0.0)
    assert not e["ghost"].valid and np.isnan(e["ghost"].pos).all() and e["ghost"].age_s == math.inf
    est.update(f, 0.005)                                  # same frame again (no new mocap data)
    assert est.counters["cf1"]["frames"] == 1 and est.counters["ghost"]["occluded"] == 1
    msg = estimates_to_msg(est.update(None, 0.006))
    assert set(msg) == {"cf1", "ghost"} and msg["cf1"]["valid"] is True


def test_deterministic_for_the_same_frames():
    rng = np.random.default_rng(3)
    frames = []
    for k in range(300):
        poses = {"cf1": (rng.normal(0, 0.002, 3) + [0.02 * k, 0, 1], yaw_quat(0.01 * k))}
        if k % 13 == 0:
            poses = {}
        if k == 100:
            poses = {"cf1": ([9.0, 9.0, 9.0], Q0)}
        frames.append(frame(k, poses))

    def run():
        est = PoseEstimator(["cf1"], alpha=0.4)
        return [est.update(f, 0.01 * i + 0.003)["cf1"] for i, f in enumerate(frames)], est.counters

    a, ca = run()
    b, cb = run()
    assert ca == cb and ca["cf1"]["outliers"] == 1
    for x, y in zip(a, b):
        assert np.array_equal(x.pos, y.pos, equal_nan=True) and np.array_equal(x.vel, y.vel, equal_nan=True)
        assert np.array_equal(x.rot, y.rot) and x.age_s == y.age_s and x.valid == y.valid


def test_quaternion_sign_kept_continuous():
    est = PoseEstimator(["cf1"])
    q = yaw_quat(0.3)
    est.update(frame(0, {"cf1": ([0, 0, 1], q)}), 0.0)
    e = est.update(frame(1, {"cf1": ([0, 0, 1], -q)}), DT)["cf1"]   # same attitude, other sign
    np.testing.assert_allclose(e.quat, q, atol=1e-12)


def test_replayed_log_reproduces_the_logged_estimates(tmp_path):
    """Fly noisy, dropping, late simulated mocap into the estimator while logging; replaying the
    log (lockstep) through a fresh estimator gives bit-identical estimates."""
    import json

    from cfrace.flight.log.writer import FlightLog, encode, read_log
    from cfrace.flight.mocap.sources import frame_to_msg, open_mocap

    class Circle:
        t = 0.0

        def poses(self):
            a = 2.0 * self.t
            return self.t, {"cf1": ([math.cos(a), math.sin(a), 1.0], yaw_quat(a)),
                             "cf2": ([0.0, 0.5 * self.t, 1.2], Q0)}

    sim = Circle()
    src = open_mocap("sim", bodies=["cf1", "cf2"], sim=sim, noise_m=0.003, latency_s=0.02,
                     dropout=0.1, seed=5)
    src.open()
    live = PoseEstimator(["cf1", "cf2"], alpha=0.4)
    path = tmp_path / "flight.mcap"
    log = FlightLog(path, {"track": "complex", "mocap": "sim"})
    for k in range(300):
        sim.t = round(sim.t + DT, 9)
        f = src.read(0.0)
        if f is None:
            continue
        log.write("/mocap/pose", sim.t, frame_to_msg(f))
        log.write("/estimate", sim.t, estimates_to_msg(live.update(f, sim.t)))
    log.close()

    data = read_log(path)
    logged = data.messages("/estimate")
    replay = open_mocap(f"replay://{path}?speed=0", bodies=["cf1", "cf2"])
    replay.open()
    again = PoseEstimator(["cf1", "cf2"], alpha=0.4)
    for (t, want), (t_pose, _) in zip(logged, data.messages("/mocap/pose")):
        got = json.loads(encode(estimates_to_msg(again.update(replay.read(), t_pose))))
        assert got == want
    assert replay.read() is None and len(logged) > 250
    assert again.counters == live.counters


def _axis_quat(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])


def _qmul(a, b) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


@pytest.mark.parametrize("lead", [0.005, 0.01, 0.03])
def test_latency_compensation_predicts_the_pose_lead_s_ahead(lead):
    """A drone turning at constant body rates (6 rad/s about a tilted body axis, from a tilted
    start) and moving at constant velocity: with lead_s the estimate is the pose lead_s after the
    newest frame, in position and attitude; the velocity is the measured one."""
    v = np.array([2.0, -1.0, 0.5])
    omega = 6.0 * np.array([0.6, -0.3, 0.74]) / np.linalg.norm([0.6, -0.3, 0.74])   # body frame, rad/s
    q_start = _axis_quat([1.0, 1.0, 0.0], 0.7)
    w_norm, w_axis = np.linalg.norm(omega), omega / np.linalg.norm(omega)

    def pose(t):   # world-from-body: q(t) = q_start exp(omega t / 2), body rates constant
        return v * t, _qmul(q_start, _axis_quat(w_axis, w_norm * t))

    est, plain = PoseEstimator(["cf1"], lead_s=lead), PoseEstimator(["cf1"])
    for k in range(20):
        f = frame(k, {"cf1": pose(k * DT)})
        e, e0 = est.update(f, now=k * DT)["cf1"], plain.update(f, now=k * DT)["cf1"]
    p_true, q_true = pose(19 * DT + lead)
    np.testing.assert_allclose(e.pos, p_true, atol=1e-9)
    np.testing.assert_allclose(e.rot, quat_to_rot(q_true), atol=1e-4)   # small-angle rate estimate
    np.testing.assert_allclose(e.vel, v, atol=1e-9)
    # without compensation the estimate is the newest frame's pose, lead_s behind the truth
    np.testing.assert_allclose(e0.pos, pose(19 * DT)[0], atol=1e-12)
    np.testing.assert_allclose(e0.rot, quat_to_rot(pose(19 * DT)[1]), atol=1e-12)
    assert np.abs(e0.rot - quat_to_rot(q_true)).max() > 10 * np.abs(e.rot - quat_to_rot(q_true)).max()
    # between frames the prediction runs on from the newest frame: lead_s plus the frame's age
    e = est.update(None, now=19 * DT + 0.004)["cf1"]
    np.testing.assert_allclose(e.pos, pose(19 * DT + 0.004 + lead)[0], atol=1e-9)
    with pytest.raises(ValueError, match="lead_s"):
        PoseEstimator(["cf1"], lead_s=-0.01)


@pytest.mark.parametrize("alpha", [1.0, 0.5])
def test_latency_compensation_flies_the_commanded_thrust_forward(alpha):
    """A level drone climbing at 2 m/s^2 under a steady command of g + 2 m/s^2 of collective
    acceleration, its poses 20 ms old: told the command, the estimator puts it where
    it is now and at its speed now, exactly (a quadratic path; a filtered pose difference lags the
    frame by dt (1/alpha - 1/2)); without the command, or with the rule off (the replay of a log
    from before it), position goes on at the lagging velocity and falls short."""
    lead, up = 0.020, 2.0
    path = lambda t: np.array([0.5 * t, 0.0, 1.0 + 0.5 * up * t * t])   # x at 0.5 m/s, z accelerating
    speed = lambda t: np.array([0.5, 0.0, up * t])
    out = {}
    for told, rule in ((True, "commanded_always"), (False, "commanded_always"), (True, "velocity")):
        est = PoseEstimator(["cf1"], alpha=alpha, lead_s=lead, prediction=rule)
        for k in range(40):
            if told:
                est.command("cf1", 9.81 + up)
            e = est.update(frame(k, {"cf1": (path(k * DT), Q0)}), now=k * DT)["cf1"]
        out[told, rule] = e
    t_now = 39 * DT + lead
    np.testing.assert_allclose(out[True, "commanded_always"].pos, path(t_now), atol=1e-9)
    np.testing.assert_allclose(out[True, "commanded_always"].vel, speed(t_now), atol=1e-6 if alpha < 1 else 1e-9)
    for other in (out[False, "commanded_always"], out[True, "velocity"]):
        assert abs(other.pos[2] - path(t_now)[2]) > 1e-4 and abs(other.vel[2] - speed(t_now)[2]) > 0.04
    est.command("cf1", None)            # no longer on rate setpoints: forgotten
    assert est._commands == {}


def test_without_compensation_the_command_makes_up_only_for_the_velocitys_lag():
    """Compensation off (lead_s 0): the estimate stays at the newest pose, and its velocity is the
    velocity of that pose's time under "commanded_always" (today's rule), the filtered pose
    difference's lag (dt (1/alpha - 1/2)) made up for by the command; "commanded" (the rule of logs
    from 2026-12-07, only with compensation) and "velocity" keep the lagging velocity. An unknown
    rule is refused."""
    up, alpha = 2.0, 0.5
    path = lambda t: np.array([0.5 * t, 0.0, 1.0 + 0.5 * up * t * t])
    out = {}
    for rule in PREDICTIONS:
        est = PoseEstimator(["cf1"], alpha=alpha, prediction=rule)
        for k in range(40):
            est.command("cf1", 9.81 + up)
            e = est.update(frame(k, {"cf1": (path(k * DT), Q0)}), now=k * DT)["cf1"]
        out[rule] = e
        np.testing.assert_allclose(e.pos, path(39 * DT), atol=1e-12)
    np.testing.assert_allclose(out["commanded_always"].vel[2], up * 39 * DT, atol=1e-6)
    for rule in ("commanded", "velocity"):
        np.testing.assert_allclose(out[rule].vel, out["velocity"].vel, atol=0)
        assert up * 39 * DT - out[rule].vel[2] > 0.5 * up * DT * (1 / alpha - 0.5)
    with pytest.raises(ValueError, match="prediction must be one of"):
        PoseEstimator(["cf1"], prediction="commanded_later")
