"""Races and evaluations fly a policy trained on the flight stack's path (metadata ``flight_obs``,
`cfrace train --flight-obs` / `--lab-loop`) on that path: velocities as the 10 ms pose difference
and thrust at least the firmware's least non-zero command, as RaceEnv gave them in training."""

from dataclasses import replace

import numpy as np

from cfrace.drone import load_profile
from cfrace.contract.actions import FIRMWARE_MIN_THRUST_COUNTS
from cfrace.evaluate.entrants import load_entrant
from cfrace.evaluate.rollout import rollout, start_poses
from cfrace.track import load_track

G = 9.81


class _Falling:
    """A stand-in for an OnnxPolicy: zero thrust, zero rates; keeps the observations it was given."""

    def __init__(self, meta: dict):
        self.meta, self.seen = meta, []

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        self.seen.append(obs.copy())
        act = np.zeros((obs.shape[0], 4), np.float32)
        act[:, 0] = -1.0
        return act


def _fly(flight_obs: bool, steps: int = 10, loop: bool = False):
    track, profile = load_track("lemniscate"), load_profile("cf2x_paper")
    ds = load_entrant("ds", track, obstacles=False)
    stand_in = _Falling({**ds.meta, "flight_obs": flight_obs, **({"loop": {"comp": 0.8}} if loop else {})})
    entrant = replace(ds, policy=stand_in)
    starts = start_poses(track, profile, 2, 1, obstacles=False, seed=3)   # in the air before a gate, at rest
    rec = rollout(track, profile, False, [entrant], np.zeros((2, 1), np.int64), starts, laps=1,
                  time_limit_s=steps * 0.02)
    return stand_in.seen, rec, profile


def test_a_flight_obs_policy_sees_the_pose_difference_of_the_last_10_ms():
    seen_exact, rec_exact, _ = _fly(False)
    seen_flight, rec_flight, _ = _fly(True)
    k = 6   # the observation before step 7: 0.12 s of fall, well above the floor
    v_exact = np.linalg.norm(seen_exact[k][:, :3], axis=-1)    # solo36: body-frame velocity first
    v_flight = np.linalg.norm(seen_flight[k][:, :3], axis=-1)
    # falling at ~g, the 10 ms difference is the speed 5 ms ago: about g * 5 ms (0.049 m/s) lower
    assert np.all(v_exact > 1.0)
    lag = v_exact - v_flight
    assert np.all((lag > 0.3 * G * 0.005) & (lag < 2.0 * G * 0.005)), lag
    assert np.all(np.linalg.norm(seen_flight[0][:, :3], axis=-1) == 0.0)   # at rest: no difference yet


def test_a_flight_obs_policy_keeps_the_firmwares_least_thrust_and_others_do_not():
    _, rec_exact, profile = _fly(False)
    _, rec_flight, _ = _fly(True)
    floor_n = float(profile.thrust_curve.to_newtons(FIRMWARE_MIN_THRUST_COUNTS))
    assert floor_n > 0.0
    # the floored thrust slows the fall: the speed after 10 steps is lower by about floor/m * t
    t = 10 * 0.02
    slower = rec_exact.speed[9] - rec_flight.speed[9]
    expected = floor_n / profile.mass * t
    assert np.all(slower > 0.5 * expected) and np.all(slower < 1.5 * expected + 1e-3), (slower, expected)


def test_a_lab_loop_policy_sees_the_difference_brought_to_the_poses_time_by_the_last_command():
    """Metadata ``loop`` (`cfrace train --lab-loop`): the lab loop at zero latency and the flight
    stack's estimator correct the 10 ms difference by the last command (cfrace.loopmodel.
    predict_commanded over half the frame gap); the batched races give it the same."""
    seen_flight, _, _ = _fly(True)
    seen_loop, rec_loop, _ = _fly(True, loop=True)
    assert np.all(np.linalg.norm(seen_loop[0][:, :3], axis=-1) == 0.0)   # no command yet: nothing to add
    k = 6
    v_flight = np.linalg.norm(seen_flight[k][:, :3], axis=-1)
    v_loop = np.linalg.norm(seen_loop[k][:, :3], axis=-1)
    # the falling policy commands no thrust: the command's acceleration is -g, over 5 ms (the floor
    # of the delivered thrust is not part of the command); the drones fall the same way
    assert np.allclose(v_loop - v_flight, G * 0.005, atol=2e-3), v_loop - v_flight
