"""The simulated firmware's modes without UDP: estimator, planner, PID cascade, commander priorities."""

import errno
import math

import numpy as np
import pytest

from cfrace.errors import ConfigError
from cfrace.simcf.controller import ABS, VELOCITY, Setpoint
from cfrace.simcf.estimator import PositionEstimator
from cfrace.simcf.firmware import SimFleet, quat_to_euler
from cfrace.simcf.planner import Planner, in_group
from cfrace.simcf.trajectory import poly7_nojerk, polyval


def fleet(profile="cf2x_paper", decks=("lighthouse",), drones=1):
    f = SimFleet("lemniscate", profile, drones, arming_required=True, decks=decks)
    for i in range(drones):
        f.arm(i, True)
    f.advance(0.1)
    return f


def run(f, seconds, each=None):
    """Advance in 10 ms steps, calling each(k) first; -> ground-truth positions (K, 3) of drone 0."""
    out = []
    for k in range(int(round(seconds / 0.01))):
        if each is not None:
            each(k)
        f.advance(0.01)
        out.append(f.state(0)["pos"].copy())
    return np.array(out)


def position_sp(x, y, z, yaw=0.0):
    sp = Setpoint(mode_x=ABS, mode_y=ABS, mode_z=ABS, mode_yaw=ABS, source="position")
    sp.position[:] = (x, y, z)
    sp.attitude[2] = yaw
    return sp


def test_estimator_reset_measurements_and_drift():
    est = PositionEstimator((), seed=1)
    est.reset((1.0, 2.0, 0.0))
    var_p, var_v = est.variances()
    assert list(var_p) == [1e4, 1e4, 1.0] and var_v[0] == pytest.approx(1e-4)    # the firmware's reset
    assert list(est.pos) == [1.0, 2.0, 0.0]
    est.external_position((3.0, -1.0, 0.5), 0.01, t=0.0)
    assert est.pos == pytest.approx([3.0, -1.0, 0.5], abs=1e-3) and est.variances()[0].max() < 1.1e-4
    est.external_position((np.nan, 0.0, 0.0), 0.01, t=0.01)                # dropped
    assert np.all(np.isfinite(est.pos))
    for _ in range(100):                                                  # 1 s without a position source
        est.predict(np.zeros(3), 0.01, (0.5, 1.0), 0.0, 0.0)
    var_after = est.variances()[0]
    assert var_after[0] > 10 * 1e-4 and var_after[2] > var_after[0]     # z's process noise is larger
    assert np.linalg.norm(est.pos - [3.0, -1.0, 0.5]) < 0.2              # drifts slowly (noisy accelerometer)


def test_kalman_reset_param_and_decks():
    f = fleet(decks=())
    est = f._fw[0].estimator
    truth = f.state(0)["pos"]
    assert np.linalg.norm(est.pos - truth) > 1.0          # no positioning source: still at initial (0, 0, 0)
    f.set_param(0, "kalman.initialX", truth[0])
    f.set_param(0, "kalman.initialY", truth[1])
    f.set_param(0, "kalman.resetEstimation", 1)
    f.advance(0.01)
    assert f.get_param(0, "kalman.resetEstimation") == 0          # the firmware clears the request
    assert est.pos[:2] == pytest.approx(truth[:2], abs=1e-3)
    logs = f.log_values(0)
    assert logs["kalman.varX"] > 1e3 and logs["kalman.varZ"] > 0.5
    for _ in range(5):
        f.external_position(0, truth)
        f.advance(0.01)
    assert f.log_values(0)["kalman.varX"] < 1e-3
    flow = fleet(decks=("flow",))
    assert flow.get_param(0, "deck.bcFlow2") == 1 and flow.get_param(0, "deck.bcLighthouse4") == 0
    assert flow.log_values(0)["range.zrange"] == pytest.approx(1000 * flow.state(0)["pos"][2])
    with pytest.raises(ConfigError, match="unknown deck"):
        SimFleet("lemniscate", "cf2x_paper", 1, decks=("sonar",))


def test_poly7_meets_its_boundary_conditions():
    c = poly7_nojerk(1.0, 0.5, -0.2, 3.0, 0.0, 0.0, 2.0)
    assert [polyval(c, 0.0, d) for d in range(4)] == pytest.approx([1.0, 0.5, -0.2, 0.0], abs=1e-9)
    assert [polyval(c, 2.0, d) for d in range(4)] == pytest.approx([3.0, 0.0, 0.0, 0.0], abs=1e-9)


def test_planner_rules():
    p = Planner()
    assert p.takeoff((0, 0, 0), 0.0, 1.0, 0.0, 2.0, t=0.0) == 0 and p.state == "flying"
    assert p.takeoff((0, 0, 0), 0.0, 1.0, 0.0, 2.0, t=0.1) == 1          # only from idle
    g = p.evaluate(1.0)
    assert g.pos[2] == pytest.approx(0.5, abs=1e-6) and g.vel[2] > 0      # symmetric: half way at half time
    assert p.evaluate(5.0).pos[2] == pytest.approx(1.0) and p.state == "flying"   # holds the goal
    assert p.land((0, 0, 1), 0.0, 0.0, 0.0, 2.0, t=5.0) == 0 and p.state == "landing"
    assert p.land((0, 0, 1), 0.0, 0.0, 0.0, 2.0, t=5.1) == 1
    p.evaluate(7.1)
    assert p.state == "idle"                                             # landed: motors off
    start = Planner.at_rest((1.0, 1.0, 1.0), math.pi - 0.1)
    p.go_to(start, relative=True, linear=False, goal=(1.0, 0.0, 0.0), yaw=0.2, duration=1.0, t=10.0)
    end = p.evaluate(11.0)
    assert end.pos == pytest.approx([2.0, 1.0, 1.0]) and math.remainder(end.yaw - (math.pi + 0.1), 2 * math.pi) \
        == pytest.approx(0.0, abs=1e-9)                                  # yaw the short way, across +-pi
    assert in_group(0, 0b10) and in_group(0b110, 0b10) and not in_group(0b01, 0b10) and not in_group(0b01, 0)


@pytest.mark.parametrize("profile", ["cf2x_paper", "cf21bl"])
def test_high_level_take_off_holds_and_lands_softly(profile):
    f = fleet(profile)
    x0, y0, _ = f.state(0)["pos"]
    assert f.high_level(0, "takeoff", height=1.0, yaw=None, duration=2.0) == 0
    hold = run(f, 4.0)[-100:]
    assert np.abs(hold - [x0, y0, 1.0]).max() < 0.1
    assert f.high_level(0, "land", height=0.0, yaw=None, duration=2.5) == 0
    vz = []
    run(f, 3.5, lambda k: vz.append(f.state(0)["vel"][2]))
    assert max(-v for v in vz) < 1.0 and f.state(0)["pos"][2] < 0.02
    st = f.status(0)
    # landed and still armed (it needs arming): the props idle at powerDist.idleThrust
    assert st["thrust"] == pytest.approx(f.idle_thrust(0)) and st["high_level"] == "idle" and not st["crashed"]


def test_high_level_refused_while_disarmed_and_by_group():
    f = SimFleet("lemniscate", "cf2x_paper", 2, arming_required=True)
    assert f.high_level(0, "takeoff", height=1.0, yaw=None, duration=2.0) == errno.EBUSY
    assert "refused" in " ".join(f.drain_events(0))
    f.arm(0, True)
    f.arm(1, True)
    f.advance(0.5)   # the estimate boots at kalman.initialX/Y/Z and initialYaw: the deck brings it round first
    f.high_level(1, "set_group_mask", group_mask=0b10)
    f.high_level(0, "takeoff", 0b10, height=1.0, yaw=None, duration=1.0)
    f.high_level(1, "takeoff", 0b10, height=1.0, yaw=None, duration=1.0)
    f.advance(1.5)
    assert f.state(0)["pos"][2] < 0.02 and f.state(1)["pos"][2] > 0.8   # only drone 1 is in group 2


def test_low_level_overrides_and_notify_stop_hands_back():
    f = fleet()
    x0, y0, _ = f.state(0)["pos"]
    f.high_level(0, "takeoff", height=0.8, yaw=None, duration=1.5)
    run(f, 2.0)
    run(f, 1.0, lambda k: f.low_level_setpoint(0, position_sp(x0 + 0.3, y0, 0.8)))
    st = f.status(0)
    assert st["setpoint_source"] == "position" and st["high_level"] == "idle" and st["priority"] == 2
    # the gap-free hand-back: the high-level command first (its setpoints wait below the low-level
    # priority), then notify-stop: the plan's setpoint is next, the motors never stop
    f.high_level(0, "go_to", x=x0, y=y0, z=0.5, yaw=0.0, duration=1.0)
    f.notify_setpoint_stop(0)
    thrust = []
    pos = run(f, 2.0, lambda k: thrust.append(f.status(0)["thrust"]))
    assert min(thrust) > 0.0 and np.abs(pos[-1] - [x0, y0, 0.5]).max() < 0.1
    # notify-stop with no plan: the high-level commander is idle and its stop setpoint turns the motors off
    run(f, 0.3, lambda k: f.low_level_setpoint(0, position_sp(x0, y0, 0.5)))
    f.notify_setpoint_stop(0)
    f.advance(0.02)
    assert f.status(0)["thrust"] == pytest.approx(f.idle_thrust(0)) and f.status(0)["setpoint_source"] == "high-level stop"


def test_velocity_and_hover_setpoints_fly_in_their_frames():
    f = fleet()
    f.high_level(0, "takeoff", height=0.6, yaw=0.0, duration=1.5)   # faces world +x after the take-off
    run(f, 2.5)
    p0 = f.state(0)["pos"].copy()

    def world(k):
        sp = Setpoint(mode_x=VELOCITY, mode_y=VELOCITY, mode_z=VELOCITY, mode_yaw=VELOCITY, source="velocity_world")
        sp.velocity[:] = (0.0, 0.4, 0.0)
        f.low_level_setpoint(0, sp)
    pos = run(f, 1.5, world)
    assert pos[-1][1] - p0[1] == pytest.approx(0.5, abs=0.15) and abs(pos[-1][0] - p0[0]) < 0.1
    _, _, yaw = quat_to_euler(f.state(0)["quat"])
    assert abs(yaw) < math.radians(5)
    f.high_level(0, "go_to", x=p0[0], y=p0[1], z=0.6, yaw=math.pi / 2, duration=1.5)   # turn to face +y
    f.notify_setpoint_stop(0)
    run(f, 2.5)

    def hover(k):
        sp = Setpoint(mode_x=VELOCITY, mode_y=VELOCITY, mode_z=ABS, mode_yaw=VELOCITY, velocity_body=True,
                      source="hover")
        sp.velocity[:2], sp.position[2] = (0.4, 0.0), 0.6
        f.low_level_setpoint(0, sp)
    pos = run(f, 1.5, hover)                                          # body forward = world +y now
    assert pos[-1][1] - p0[1] == pytest.approx(0.5, abs=0.15) and abs(pos[-1][0] - p0[0]) < 0.1
    assert pos[-1][2] == pytest.approx(0.6, abs=0.05)


def test_position_setpoint_watchdog_holds_then_stops():
    f = fleet()
    x0, y0, _ = f.state(0)["pos"]
    run(f, 2.0, lambda k: f.low_level_setpoint(0, position_sp(x0, y0, 0.7)))
    run(f, 1.0)
    assert f.status(0)["watchdog"] == "level" and abs(f.state(0)["pos"][2] - 0.7) < 0.1   # position still held
    run(f, 1.5)
    assert f.status(0)["watchdog"] == "shutdown" and f.status(0)["thrust"] == 0.0


def test_controller_selection_battery_and_logs():
    f = fleet()
    f.set_param(0, "stabilizer.controller", 2)                       # Mellinger: emulated
    assert not any("not emulated" in e for e in f.drain_events(0))
    f.set_param(0, "stabilizer.controller", 3)                       # INDI: not emulated, PID runs
    assert any("not emulated" in e for e in f.drain_events(0))
    assert f.log_values(0)["pm.state"] == 0
    f.set_battery(0, 0.0)
    f.advance(4.9)                   # pm_stm32f4.c: low power after 5 s below pm.lowVoltage
    logs = f.log_values(0)
    assert logs["pm.vbat"] < f.get_param(0, "pm.lowVoltage") and logs["pm.state"] == 0
    f.advance(0.2)
    logs = f.log_values(0)
    assert logs["pm.state"] == 3
    assert logs["pm.batteryLevel"] == pytest.approx(0.0, abs=0.1)
    f.set_battery(0, 0.9)
    x0, y0, _ = f.state(0)["pos"]
    run(f, 1.5, lambda k: f.low_level_setpoint(0, position_sp(x0, y0, 0.5)))
    logs = f.log_values(0)
    assert logs["ctrltarget.z"] == pytest.approx(0.5) and logs["posCtl.targetZ"] == pytest.approx(0.5)
    assert logs["stabilizer.thrust"] > 10000 and logs["controller.cmd_thrust"] > 10000
    assert min(logs[f"motor.m{k}"] for k in range(1, 5)) > 0 and min(logs[f"rpm.m{k}"] for k in range(1, 5)) > 1000
    assert logs["acc.z"] == pytest.approx(1.0, abs=0.2)               # hovering: 1 g on the body z axis
    idle = f.battery.volts(f._fw[0].charge, f.battery.idle_amps)
    assert logs["pm.vbat"] < idle - 0.1                                # sags under load
