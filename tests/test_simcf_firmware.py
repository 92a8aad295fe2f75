"""SimFleet firmware logic without UDP: conventions, unlock, watchdog, arming, emergency stop."""

import math

import numpy as np
import pytest

from cfrace.errors import ConfigError
from cfrace.simcf.firmware import MAX_THRUST, SimFleet, quat_to_euler
from cfrace.simcf.physics import OneWorld


class RecordingSim(OneWorld):
    """The real one-world simulator, recording every command it is given."""

    def __init__(self, *a, **k):
        self.log = []
        super().__init__(*a, **k)

    def step(self, thrust, rates, substeps=10):
        self.log.append((np.array(thrust, float), np.array(rates, float), substeps))
        super().step(thrust, rates, substeps)


def make(drones=1, arming_required=False, recording=True, **kw):
    from cfrace.drone import load_profile
    from cfrace.sim.simulator import CrashRules
    from cfrace.track import load_track

    track, profile = load_track("lemniscate"), load_profile("cf2x_paper")
    sim = (RecordingSim(track, profile, drones, obstacles=True, rules=CrashRules(floor_grace_s=None, arena=False))
           if recording else None)
    return SimFleet(track, profile, drones, arming_required=arming_required, sim=sim, **kw)


def last_cmd(fleet, i=0):
    thrust, rates, _ = fleet.sim.log[-1]
    return thrust[i], rates[i]


def rate_mode(fleet, i=0):
    fleet.set_param(i, "flightmode.stabModeRoll", 0)
    fleet.set_param(i, "flightmode.stabModePitch", 0)


def test_zero_thrust_unlock_and_thrust_limits():
    f = make()
    rate_mode(f)
    f.handle_setpoint(0, 0, 0, 0, 40000)        # before the unlock: nothing
    f.advance(0.01)
    assert last_cmd(f)[0] == 0.0 and f.status(0)["locked"]
    f.handle_setpoint(0, 0, 0, 0, 0)            # unlock
    f.handle_setpoint(0, 0, 0, 0, 40000)
    f.advance(0.01)
    assert last_cmd(f)[0] == pytest.approx(f.profile.thrust_curve.to_newtons(40000))
    f.handle_setpoint(0, 0, 0, 0, 500)          # below MIN_THRUST -> 0
    f.advance(0.01)
    assert last_cmd(f)[0] == 0.0
    f.handle_setpoint(0, 0, 0, 0, 65535)        # capped at MAX_THRUST
    f.advance(0.01)
    assert last_cmd(f)[0] == pytest.approx(f.profile.thrust_curve.to_newtons(MAX_THRUST))
    assert f.status(0)["thrust_counts"] == MAX_THRUST


def test_the_flight_loops_least_thrust_keeps_rate_control():
    """The flight loop sends at least FLYING_MIN_COUNTS while a drone races: at that command the
    firmware still controls the body rates (as the training simulator does at zero thrust); one
    count less is zero thrust, rates off."""
    from cfrace.flight.loop.flight_loop import FLYING_MIN_COUNTS
    from cfrace.simcf.firmware import MIN_THRUST

    assert FLYING_MIN_COUNTS == MIN_THRUST
    f = make()
    rate_mode(f)
    f.handle_setpoint(0, 0, 0, 0, 0)
    f.handle_setpoint(0, 90.0, 0.0, 0.0, FLYING_MIN_COUNTS)
    f.advance(0.01)
    thrust, rates = last_cmd(f)
    assert 0.0 < thrust < 0.05 * f.profile.weight
    np.testing.assert_allclose(rates, np.radians([90.0, 0.0, 0.0]))
    f.handle_setpoint(0, 90.0, 0.0, 0.0, FLYING_MIN_COUNTS - 1)
    f.advance(0.01)
    thrust, rates = last_cmd(f)
    assert thrust == 0.0 and not rates.any()


def test_rate_mode_conventions():
    """Packet values (after cflib's pitch negation) -> body rates p = roll, q = -pitch, r = -yaw."""
    f = make()
    rate_mode(f)
    f.handle_setpoint(0, 0, 0, 0, 0)
    f.handle_setpoint(0, 10.0, 20.0, 30.0, 45000)
    f.advance(0.01)
    thrust, rates = last_cmd(f)
    assert thrust > 0
    np.testing.assert_allclose(rates, np.radians([10.0, -20.0, -30.0]))


def test_angle_mode_is_default_and_tracks_angles():
    f = make()
    assert f.get_param(0, "flightmode.stabModeRoll") == 1 and f.get_param(0, "flightmode.stabModePitch") == 1
    f.handle_setpoint(0, 0, 0, 0, 0)
    f.handle_setpoint(0, 10.0, 10.0, 0.0, 45000)   # roll right, packet pitch +10 = nose up
    f.advance(0.01)
    _, rates = last_cmd(f)
    assert rates[0] > 0 and rates[1] < 0 and rates[2] == 0.0
    for k in range(140):                              # lift off level, then 1 s at the setpoint
        f.handle_setpoint(0, 10.0 * (k >= 40), 10.0 * (k >= 40), 0.0, 45000)
        f.advance(0.01)
    roll, pitch, _ = quat_to_euler(f.state(0)["quat"])
    assert math.degrees(roll) == pytest.approx(10.0, abs=1.0)
    assert math.degrees(pitch) == pytest.approx(-10.0, abs=1.0)


def test_yaw_angle_mode_not_inverted():
    f = make()
    f.set_param(0, "flightmode.stabModeYaw", 1)
    f.handle_setpoint(0, 0, 0, 0, 0)
    f.handle_setpoint(0, 0, 0, 10.0, 45000)
    f.advance(0.01)
    _, rates = last_cmd(f)
    # the attitude error is against the estimate, which at boot faces kalman.initialYaw (0), not the start yaw
    assert f.get_param(0, "kalman.initialYaw") == 0.0 and abs(f._start_yaw) > 0.1
    assert rates[2] == pytest.approx(6.0 * math.radians(10.0), abs=0.02)


def test_watchdog_levels_out_then_shuts_down_and_locks():
    f = make()
    rate_mode(f)
    f.handle_setpoint(0, 0, 0, 0, 0)
    f.handle_setpoint(0, 50.0, 0, 0, 50000)
    f.advance(0.49)
    assert f.status(0)["watchdog"] == "ok"
    assert last_cmd(f)[1][0] == pytest.approx(math.radians(50.0))
    f.advance(0.03)
    st = f.status(0)
    assert st["watchdog"] == "level" and 0.5 < st["setpoint_age"] <= 0.52
    thrust, rates = last_cmd(f)
    assert thrust == pytest.approx(f.profile.thrust_curve.to_newtons(50000))   # keeps the last thrust
    roll = quat_to_euler(f.state(0)["quat"])[0]
    assert roll > 0 and rates[0] < 0                                          # levelling out
    f.advance(1.5)
    assert f.status(0)["watchdog"] == "shutdown" and f.status(0)["locked"]
    assert 2.0 < f.status(0)["setpoint_age"] < 2.03
    assert last_cmd(f)[0] == 0.0
    f.handle_setpoint(0, 0, 0, 0, 50000)          # still locked
    f.advance(0.01)
    assert last_cmd(f)[0] == 0.0 and f.status(0)["watchdog"] == "ok"
    f.handle_setpoint(0, 0, 0, 0, 0)              # in flight the supervisor locked: no unlock
    f.handle_setpoint(0, 0, 0, 0, 50000)
    f.advance(0.01)
    assert last_cmd(f)[0] == 0.0 and f.status(0)["emergency_stopped"]
    assert any("500 ms" in e for e in f.drain_events(0))
    f.reboot(0)                                   # reboot required (supervisor_state_machine.c)
    f.handle_setpoint(0, 0, 0, 0, 0)
    f.handle_setpoint(0, 0, 0, 0, 50000)
    f.advance(0.01)
    assert last_cmd(f)[0] > 0.0


def test_watchdog_on_the_ground_keeps_the_zero_thrust_unlock():
    f = make()
    f.handle_setpoint(0, 0, 0, 0, 0)              # unlocked, motors off: not flying
    f.advance(2.1)
    st = f.status(0)
    assert st["watchdog"] == "shutdown" and st["locked"] and not st["emergency_stopped"]
    f.handle_setpoint(0, 0, 0, 0, 0)
    f.handle_setpoint(0, 0, 0, 0, 50000)
    f.advance(0.01)
    assert last_cmd(f)[0] > 0.0


def test_watchdog_boundaries_are_exact_within_one_step():
    f = make()
    f.handle_setpoint(0, 0, 0, 0, 0)
    f.advance(0.5)
    assert f.status(0)["watchdog"] == "ok"
    f.advance(0.002)
    assert f.status(0)["watchdog"] == "level"


def test_arming_required():
    f = make(arming_required=True)
    rate_mode(f)
    assert not f.status(0)["armed"]
    f.handle_setpoint(0, 0, 0, 0, 0)
    f.handle_setpoint(0, 0, 0, 0, 50000)
    f.advance(0.01)
    assert last_cmd(f)[0] == 0.0
    assert f.arm(0, True)
    f.advance(0.01)
    assert last_cmd(f)[0] > 0.0
    f.arm(0, False)
    f.advance(0.01)
    assert last_cmd(f)[0] == 0.0
    bits = f.supervisor_bitfield(0)
    assert bits & 1 and not bits & 2           # can be armed, not armed


def test_emergency_stop_needs_reboot():
    f = make(arming_required=True)
    f.arm(0, True)
    f.handle_setpoint(0, 0, 0, 0, 0)
    f.handle_setpoint(0, 0, 0, 0, 50000)
    f.advance(0.01)
    assert last_cmd(f)[0] > 0
    f.emergency_stop(0)
    f.handle_setpoint(0, 0, 0, 0, 0)
    f.handle_setpoint(0, 0, 0, 0, 50000)
    f.advance(0.01)
    st = f.status(0)
    assert last_cmd(f)[0] == 0.0 and st["emergency_stopped"] and not st["armed"]
    assert not f.arm(0, True)
    assert f.supervisor_bitfield(0) & (1 << 6)   # locked
    f.reboot(0)
    assert f.arm(0, True) and not f.status(0)["emergency_stopped"]


def test_stop_param_and_emergency_stop_watchdog():
    f = make(drones=2)
    f.set_param(0, "stabilizer.stop", 1)
    assert f.status(0)["emergency_stopped"] and not f.status(1)["emergency_stopped"]
    f.feed_emergency_stop_watchdog(1)
    f.advance(0.9)
    assert not f.status(1)["emergency_stopped"]
    f.advance(0.2)
    assert f.status(1)["emergency_reason"] == "emergency-stop watchdog"


def test_params_errors_and_coercion():
    f = make()
    with pytest.raises(KeyError):
        f.set_param(0, "nope.nothing", 1)
    with pytest.raises(PermissionError):
        f.set_param(0, "supervisor.armingReq", 0)
    assert f.set_param(0, "flightmode.stabModeRoll", 256) == 0      # uint8 wraps like the firmware
    with pytest.raises(IndexError):
        f.get_param(3, "flightmode.stabModeRoll")


def test_default_start_grid_and_poses():
    f = make(drones=2, recording=False)
    track = f.track
    gx, gy, _, gyaw = track.gates[0]
    t, poses = f.poses()
    assert t == 0.0 and list(poses) == ["cf1", "cf2"]
    p1, q1 = poses["cf1"]
    p2, _ = poses["cf2"]
    assert p1.dtype == np.float64 and p1.shape == (3,) and q1.shape == (4,)
    assert np.linalg.norm(p1 - p2) == pytest.approx(track.spawn.opponent_offset)
    n = np.array([math.cos(gyaw), math.sin(gyaw)])
    mid = (p1[:2] + p2[:2]) / 2 - np.array([gx, gy])
    assert mid @ n == pytest.approx(track.spawn.ground_distance)        # on the +n side
    assert p1[2] == pytest.approx(f.profile.collision_box[2] / 2)
    yaw = quat_to_euler(q1)[2]
    assert math.cos(yaw - gyaw) == pytest.approx(-1.0, abs=1e-6)         # facing the gate


def test_construction_errors_and_names():
    with pytest.raises(ConfigError):
        make(drones=2, body_names=["a"])
    with pytest.raises(ConfigError):
        make(drones=2, start_positions=np.zeros((3, 3)))
    f = make(drones=2, body_names=["red", "blue"], start_positions=[[0, 3, 0.015], [1, 3, 0.015]])
    assert list(f.poses()[1]) == ["red", "blue"]
    np.testing.assert_allclose(f.poses()[1]["blue"][0], [1, 3, 0.015], atol=1e-9)


def test_advance_carries_the_remainder():
    f = make()
    assert f.advance(0.003) == 1
    assert f.advance(0.003) == 2
    assert f.time == pytest.approx(0.006)


def test_hover_lifts_off_the_same_in_every_backend():
    """Hover thrust + 30 % lifts a drone off the floor in every backend, the same way."""
    from cfrace.drone import load_profile

    prof = load_profile("cf2x_paper")
    counts = int(prof.thrust_curve.to_counts(prof.weight * 1.3))
    heights = []
    for backend in ("c", "torch"):
        f = SimFleet("lemniscate", prof, 1, arming_required=False, backend=backend)
        rate_mode(f)
        f.handle_setpoint(0, 0, 0, 0, 0)
        for _ in range(20):
            f.handle_setpoint(0, 0, 0, 0, counts)
            f.advance(0.02)
        heights.append(f.state(0)["pos"][2])
    assert heights[0] > 0.1 and f.status(0)["crash_reason"] == ""
    assert heights[0] == pytest.approx(heights[1], abs=1e-3)


def test_unpowered_drone_falls_and_crashes_on_the_floor():
    f = make(start_positions=[[0.0, 4.0, 1.5]])
    f.advance(0.7)                                  # no setpoint ever: motors off, free fall
    st = f.status(0)
    assert st["watchdog"] == "idle" and st["crashed"] and st["crash_reason"] == "floor"
    assert f.supervisor_bitfield(0) & (1 << 7)
