"""The REAL cflib client (UDP driver) against SimCrazyflieServer on 127.0.0.1, in real time."""

import math
import time

import numpy as np
import pytest

cflib = pytest.importorskip("cflib")
import cflib.crtp  # noqa: E402
from cflib.crazyflie.log import LogConfig  # noqa: E402
from cflib.crazyflie.syncLogger import SyncLogger  # noqa: E402

from cfrace.simcf.firmware import SimFleet, quat_to_euler  # noqa: E402
from cfrace.simcf.server import SimCrazyflieServer  # noqa: E402
from cflibtools import connect, wait_for  # noqa: E402

cflib.crtp.init_drivers()


@pytest.fixture
def served():
    fleet = SimFleet("lemniscate", "cf2x_paper", 2, arming_required=True)
    with SimCrazyflieServer(fleet, base_port=0) as server:
        yield fleet, server


def rate_mode(cf):
    cf.param.set_value("flightmode.stabModeRoll", 0)
    cf.param.set_value("flightmode.stabModePitch", 0)
    assert wait_for(lambda: cf.param.get_value("flightmode.stabModeRoll") == "0"
                    and cf.param.get_value("flightmode.stabModePitch") == "0")


def counts(fleet, weights):
    return int(fleet.profile.thrust_curve.to_counts(fleet.profile.weight * weights))


def send_for(cf, seconds, roll=0.0, pitch=0.0, yawrate=0.0, thrust=0):
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        cf.commander.send_setpoint(roll, pitch, yawrate, thrust)
        time.sleep(0.01)


def test_connect_params_and_log(served):
    fleet, server = served
    t0 = time.monotonic()
    with connect(server.uris[1]) as scf:
        assert time.monotonic() - t0 < 10.0       # answered, no retry (a loose bound: a loaded VM)
        scf.wait_for_params()
        cf = scf.cf
        assert cf.platform.get_protocol_version() == 12
        assert cf.param.get_value("flightmode.stabModeRoll") == "1"        # firmware default: angle
        rate_mode(cf)
        assert fleet.get_param(1, "flightmode.stabModeRoll") == 0
        assert fleet.get_param(0, "flightmode.stabModeRoll") == 1          # drone 0 has its own params
        conf = LogConfig("state", period_in_ms=20)
        for name in ("stateEstimate.x", "stateEstimate.z", "pm.vbat"):
            conf.add_variable(name, "float")
        with SyncLogger(scf, conf) as logger:
            for k, (ts, data, _) in enumerate(logger):
                if k == 3:
                    break
        # the estimate (Lighthouse deck by default) within millimetres of the truth; the battery model
        assert data["stateEstimate.x"] == pytest.approx(fleet.state(1)["pos"][0], abs=0.01)
        assert data["stateEstimate.z"] == pytest.approx(fleet.profile.collision_box[2] / 2, abs=0.01)
        assert 3.9 < data["pm.vbat"] < 4.2
    st = server.stats()[1]
    assert st["rx"] > 20 and st["tx"] > 20 and server.stats()[0]["rx"] == 0


def test_arming_unlock_and_hover(served):
    fleet, server = served
    with connect(server.uris[0]) as scf:
        cf = scf.cf
        scf.wait_for_params()
        rate_mode(cf)
        z0 = fleet.state(0)["pos"][2]
        cf.commander.send_setpoint(0, 0, 0, 0)                          # unlocked but not armed
        send_for(cf, 0.3, thrust=counts(fleet, 1.5))
        assert fleet.state(0)["pos"][2] == pytest.approx(z0) and fleet.status(0)["thrust"] == 0.0
        cf.supervisor.send_arming_request(True)
        assert wait_for(lambda: fleet.status(0)["armed"])
        assert "Is armed" in cf.supervisor.read_state_list()
        fleet.reboot(0)                                                  # locked again, re-arm
        cf.param.set_value("flightmode.stabModeRoll", 0)
        cf.param.set_value("flightmode.stabModePitch", 0)
        cf.supervisor.send_arming_request(True)
        assert wait_for(lambda: fleet.status(0)["armed"] and fleet.get_param(0, "flightmode.stabModePitch") == 0)
        send_for(cf, 0.3, thrust=counts(fleet, 1.5))                    # no zero-thrust unlock yet
        assert fleet.state(0)["pos"][2] == pytest.approx(z0) and fleet.status(0)["locked"]
        cf.commander.send_setpoint(0, 0, 0, 0)                          # the unlock
        xy0 = fleet.state(0)["pos"][:2]
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end:                                 # altitude P-D on ground truth
            s = fleet.state(0)
            u = np.clip(1.0 + 2.0 * (0.5 - s["pos"][2]) - 1.2 * s["vel"][2], 0.5, 1.6)
            cf.commander.send_setpoint(0, 0, 0, counts(fleet, u))
            time.sleep(0.01)
        s = fleet.state(0)
        roll, pitch, _ = quat_to_euler(s["quat"])
        assert 0.35 < s["pos"][2] < 0.65
        assert abs(s["vel"][2]) < 0.3 and np.linalg.norm(s["pos"][:2] - xy0) < 0.2
        assert abs(math.degrees(roll)) < 3 and abs(math.degrees(pitch)) < 3
        assert not fleet.status(0)["crashed"]


def test_rate_signs_through_cflib(served):
    """cflib roll +: omega_x > 0. cflib pitch + (cflib negates it): nose down, omega_y > 0 in
    x-forward/y-left/z-up body axes. cflib yaw rate + (the firmware inverts it): omega_z < 0."""
    fleet, server = served
    with connect(server.uris[0]) as scf:
        cf = scf.cf
        scf.wait_for_params()
        rate_mode(cf)
        cf.supervisor.send_arming_request(True)
        cf.commander.send_setpoint(0, 0, 0, 0)
        send_for(cf, 0.35, thrust=counts(fleet, 1.3))
        hover = counts(fleet, 1.0)
        omega = {}
        for axis, kw in (("roll", dict(roll=40.0)), ("pitch", dict(pitch=40.0)), ("yaw", dict(yawrate=40.0))):
            send_for(cf, 0.12, thrust=hover, **kw)
            omega[axis] = fleet.state(0)["omega"].copy()
            send_for(cf, 0.12, thrust=hover, **{k: -v for k, v in kw.items()})   # undo
        w40 = math.radians(40.0)
        assert omega["roll"][0] == pytest.approx(w40, rel=0.2)
        assert omega["pitch"][1] == pytest.approx(w40, rel=0.2)
        assert omega["yaw"][2] == pytest.approx(-w40, rel=0.3)
        assert abs(omega["roll"][1]) < 0.2 * w40 and abs(omega["pitch"][0]) < 0.2 * w40


def test_watchdog_over_the_wire(served):
    fleet, server = served
    with connect(server.uris[0]) as scf:
        cf = scf.cf
        scf.wait_for_params()
        rate_mode(cf)
        cf.supervisor.send_arming_request(True)
        cf.commander.send_setpoint(0, 0, 0, 0)
        send_for(cf, 0.3, thrust=counts(fleet, 1.2))
        t_last = time.monotonic()
        assert fleet.status(0)["watchdog"] == "ok"
        time.sleep(max(0.0, t_last + 0.65 - time.monotonic()))
        st = fleet.status(0)
        assert st["watchdog"] == "level" and st["thrust"] > 0.0
        time.sleep(max(0.0, t_last + 2.2 - time.monotonic()))
        st = fleet.status(0)
        assert st["watchdog"] == "shutdown" and st["locked"] and st["thrust"] == 0.0
        assert st["emergency_stopped"]                                 # in flight: locked (supervisor)
        cf.commander.send_setpoint(0, 0, 0, 0)
        send_for(cf, 0.1, thrust=counts(fleet, 1.2))
        assert fleet.status(0)["thrust"] == 0.0                        # reboot required
        assert fleet.supervisor_bitfield(0) & (1 << 6)


def test_emergency_stop_over_the_wire(served):
    fleet, server = served
    with connect(server.uris[0]) as scf:
        cf = scf.cf
        scf.wait_for_params()
        cf.supervisor.send_arming_request(True)
        cf.commander.send_setpoint(0, 0, 0, 0)
        send_for(cf, 0.2, thrust=counts(fleet, 1.3))
        assert fleet.status(0)["thrust"] > 0.0
        cf.supervisor.send_emergency_stop()
        assert wait_for(lambda: fleet.status(0)["emergency_stopped"], 0.5)
        send_for(cf, 0.1, thrust=counts(fleet, 1.3))
        assert fleet.status(0)["thrust"] == 0.0
        assert "Is locked" in cf.supervisor.read_state_list()
