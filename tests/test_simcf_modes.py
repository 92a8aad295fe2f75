"""The firmware's flight modes through the REAL cflib client over UDP, in real time: scripts that do
what cflib's examples do (logging, parameters, the motion commander, an autonomous sequence of
low-level position setpoints, the high-level commander) and checks that the drone flies what they ask.
"""

import math
import threading
import time

import numpy as np
import pytest

cflib = pytest.importorskip("cflib")
import cflib.crtp  # noqa: E402
from cflib.crazyflie.log import LogConfig  # noqa: E402
from cflib.crazyflie.syncLogger import SyncLogger  # noqa: E402
from cflib.positioning.motion_commander import MotionCommander  # noqa: E402

from cfrace.simcf.firmware import SimFleet, quat_to_euler  # noqa: E402
from cfrace.simcf.server import SimCrazyflieServer  # noqa: E402
from cflibtools import connect, wait_for  # noqa: E402

cflib.crtp.init_drivers()


def serve(decks=("lighthouse",), drones=1):
    fleet = SimFleet("lemniscate", "cf2x_paper", drones, arming_required=True, decks=decks)
    return fleet, SimCrazyflieServer(fleet, base_port=0)


def reset_estimator(scf):
    """What cflib's autonomous examples do: request a Kalman reset, then wait until the position
    variances of the last 10 samples (500 ms apart in the examples, 100 ms here) agree within 0.001."""
    cf = scf.cf
    cf.param.set_value("kalman.resetEstimation", "1")
    time.sleep(0.1)
    cf.param.set_value("kalman.resetEstimation", "0")
    conf = LogConfig(name="Kalman Variance", period_in_ms=100)
    for name in ("kalman.varPX", "kalman.varPY", "kalman.varPZ", "kalman.varX", "kalman.varY", "kalman.varZ"):
        conf.add_variable(name, "float")
    history = []
    with SyncLogger(scf, conf) as logger:
        for _, data, _ in logger:
            history.append([data[n] for n in ("kalman.varX", "kalman.varY", "kalman.varZ")])
            recent = np.array(history[-10:])
            if len(history) >= 10 and np.all(recent.max(0) - recent.min(0) < 0.001):
                return history
            assert len(history) < 100, "the position estimate never settled"


def fly_sample(fleet, i, seconds, period=0.02):
    """Ground truth of drone i sampled for ``seconds``: (t, pos (3,), vel (3,)) rows."""
    rows, t_end = [], time.monotonic() + seconds
    while time.monotonic() < t_end:
        s = fleet.state(i)
        rows.append((time.monotonic(), s["pos"], s["vel"]))
        time.sleep(period)
    return rows


def test_logging_and_parameters_as_in_cflib_examples():
    fleet, server = serve()
    with server, connect(server.uris[0]) as scf:
        cf = scf.cf
        scf.wait_for_params()
        # basic parameter example: read, write, the update callback sees the new value
        assert float(cf.param.get_value("pid_attitude.pitch_kd")) == pytest.approx(0.0)
        assert float(cf.param.get_value("pid_attitude.roll_kp")) == pytest.approx(6.0)
        assert float(cf.param.get_value("velCtlPid.vzKi")) == pytest.approx(15.0)
        assert int(cf.param.get_value("posCtlPid.thrustBase")) == round(
            float(fleet.profile.thrust_curve.to_counts(fleet.profile.weight)))
        assert float(cf.param.get_value("pid_rate.roll_kp")) == pytest.approx(fleet.profile.pid_roll_pitch.kp)
        assert cf.param.get_value("deck.bcLighthouse4") == "1" and cf.param.get_value("deck.bcFlow2") == "0"
        assert cf.param.get_value("stabilizer.controller") == "1" and cf.param.get_value("stabilizer.estimator") == "2"
        seen = threading.Event()
        cf.param.add_update_callback(group="pid_attitude", name="pitch_kd",
                                     cb=lambda name, value: seen.set() if float(value) == 0.25 else None)
        cf.param.set_value("pid_attitude.pitch_kd", 0.25)
        assert seen.wait(2.0) and fleet.get_param(0, "pid_attitude.pitch_kd") == pytest.approx(0.25)
        # basic log example: stabilizer attitude, battery, state estimate, at 10 ms
        conf = LogConfig(name="Stabilizer", period_in_ms=10)
        for name in ("stabilizer.roll", "stabilizer.pitch", "stabilizer.yaw", "pm.vbat", "stateEstimate.x",
                     "stateEstimate.z"):
            conf.add_variable(name, "float")
        stamps = []
        time.sleep(1.0)   # the attitude estimate boots facing kalman.initialYaw (0); the deck brings it round
        with SyncLogger(scf, conf) as logger:
            for ts, data, _ in logger:
                stamps.append(ts)
                if len(stamps) == 20:
                    break
        truth = fleet.state(0)
        _, _, yaw = quat_to_euler(truth["quat"])
        # the estimate (the deck's attitude, 0.01 rad noise, fused), not the truth
        assert data["stabilizer.yaw"] == pytest.approx(math.degrees(yaw), abs=1.0)
        assert abs(data["stabilizer.roll"]) < 1.0 and abs(data["stabilizer.pitch"]) < 1.0
        assert data["stateEstimate.x"] == pytest.approx(truth["pos"][0], abs=0.01)     # the Lighthouse deck
        assert data["stateEstimate.z"] == pytest.approx(truth["pos"][2], abs=0.01)
        assert 3.9 < data["pm.vbat"] < 4.2
        assert np.median(np.diff(stamps)) == pytest.approx(10, abs=1)


def test_position_setpoints_autonomous_sequence():
    """cflib's autonomous sequence: reset the estimator, wait for it, stream position setpoints at
    10 Hz through a list of waypoints, then stop. Each waypoint is reached within 0.1 m."""
    fleet, server = serve()
    with server, connect(server.uris[0]) as scf:
        cf = scf.cf
        scf.wait_for_params()
        history = reset_estimator(scf)
        assert history[-1][0] < 1e-4 and history[-1][2] < 1e-4    # the Lighthouse deck: millimetres
        cf.supervisor.send_arming_request(True)
        x0, y0, _ = fleet.state(0)["pos"]
        sequence = [(x0, y0, 0.4), (x0 + 0.4, y0, 0.4), (x0 + 0.4, y0 + 0.4, 0.6), (x0, y0, 0.2)]
        errors = []
        for x, y, z in sequence:
            for _ in range(20):
                cf.commander.send_position_setpoint(x, y, z, 0.0)
                time.sleep(0.1)
            errors.append(np.linalg.norm(fleet.state(0)["pos"] - np.array([x, y, z])))
        _, _, yaw = quat_to_euler(fleet.state(0)["quat"])
        cf.commander.send_stop_setpoint()
        cf.commander.send_notify_setpoint_stop()
        assert max(errors) < 0.1, errors
        assert abs(yaw) < math.radians(5)                         # the setpoint's yaw, 0
        assert wait_for(lambda: fleet.state(0)["pos"][2] < 0.02, 2.0) and fleet.status(0)["thrust"] == fleet.idle_thrust(0)
        assert not fleet.status(0)["crashed"]


def test_motion_commander_with_a_flow_deck():
    """cflib's motion commander demo: checks the Flow deck, takes off to 0.5 m, flies 0.5 m forward,
    turns, lands (hover setpoints built on the flow deck's velocity and height)."""
    fleet, server = serve(decks=("flow",))
    with server, connect(server.uris[0]) as scf:
        cf = scf.cf
        scf.wait_for_params()
        assert cf.param.get_value("deck.bcFlow2") == "1"
        cf.supervisor.send_arming_request(True)
        start = fleet.state(0)
        _, _, yaw0 = quat_to_euler(start["quat"])
        heading = np.array([math.cos(yaw0), math.sin(yaw0)])
        with MotionCommander(scf, default_height=0.5) as mc:
            time.sleep(0.5)
            up = fleet.state(0)["pos"]
            mc.forward(0.5, velocity=0.5)
            time.sleep(1.0)
            moved = fleet.state(0)["pos"]
            mc.turn_left(90)
            time.sleep(0.5)
            _, _, yaw1 = quat_to_euler(fleet.state(0)["quat"])
        assert up[2] == pytest.approx(0.5, abs=0.1)
        along = float(np.dot(moved[:2] - start["pos"][:2], heading))
        assert along == pytest.approx(0.5, abs=0.12), along
        assert abs(math.degrees(math.remainder(yaw1 - yaw0, 2 * math.pi)) - 90.0) < 15.0
        assert wait_for(lambda: fleet.state(0)["pos"][2] < 0.02, 2.0) and fleet.status(0)["thrust"] == fleet.idle_thrust(0)
        assert not fleet.status(0)["crashed"]


def test_high_level_commander_takeoff_go_to_land_and_hand_over():
    """Take off to 0.8 m, go to a point, low-level setpoints take over (the planner stops), the
    notify-stop hands back, and the land: touchdown slower than 0.5 m/s, then motors off."""
    fleet, server = serve()
    with server, connect(server.uris[0]) as scf:
        cf = scf.cf
        scf.wait_for_params()
        reset_estimator(scf)
        hl = cf.high_level_commander
        hl.takeoff(0.8, 2.0)                                          # refused: not armed yet
        time.sleep(0.3)
        assert fleet.state(0)["pos"][2] < 0.02 and fleet.status(0)["high_level"] == "idle"
        cf.supervisor.send_arming_request(True)
        assert wait_for(lambda: fleet.status(0)["armed"])
        x0, y0, _ = fleet.state(0)["pos"]
        hl.takeoff(0.8, 2.0)
        time.sleep(2.5)
        assert np.linalg.norm(fleet.state(0)["pos"] - [x0, y0, 0.8]) < 0.1
        assert "HL control is active" in cf.supervisor.read_state_list()
        hl.go_to(x0 + 0.5, y0 - 0.3, 1.0, 0.0, 2.0)
        time.sleep(2.5)
        assert np.linalg.norm(fleet.state(0)["pos"] - [x0 + 0.5, y0 - 0.3, 1.0]) < 0.1
        for _ in range(10):                                           # low-level takes over
            cf.commander.send_position_setpoint(x0, y0, 1.0, 0.0)
            time.sleep(0.1)
        st = fleet.status(0)
        assert st["setpoint_source"] == "position" and st["high_level"] == "idle"
        hl.go_to(x0, y0, 0.6, 0.0, 1.5)                               # the command first, then hand back
        cf.commander.send_notify_setpoint_stop()
        assert wait_for(lambda: fleet.status(0)["setpoint_source"] == "high-level", 0.5)
        time.sleep(2.0)
        assert np.linalg.norm(fleet.state(0)["pos"] - [x0, y0, 0.6]) < 0.1
        hl.land(0.0, 2.0)
        rows = fly_sample(fleet, 0, 2.8)
        z = np.array([r[1][2] for r in rows])
        vz = np.array([r[2][2] for r in rows])
        rest = fleet.profile.collision_box[2] / 2
        touch = int(np.argmax(z < rest + 0.01))
        assert z[touch] < rest + 0.01 and abs(vz[max(0, touch - 1)]) <= 0.5, (z[touch], vz[touch - 1])
        assert wait_for(lambda: fleet.status(0)["thrust"] == fleet.idle_thrust(0) and fleet.status(0)["high_level"] == "idle", 1.0)
        assert not fleet.status(0)["crashed"]


def test_mocap_example_external_pose_and_high_level_commander():
    """cflib's mocap example: a drone without positioning deck, its pose streamed as external pose
    (here: the simulator's ground truth at 100 Hz, as a mocap system would); the estimator follows
    it; the high-level commander flies; when the stream stops the estimate's variance grows."""
    fleet, server = serve(decks=())
    stop = threading.Event()
    with server, connect(server.uris[0]) as scf:
        cf = scf.cf
        scf.wait_for_params()
        assert cf.param.get_value("deck.bcLighthouse4") == "0" and cf.param.get_value("deck.bcFlow2") == "0"

        def stream():
            while not stop.is_set():
                s = fleet.state(0)
                w, x, y, z = s["quat"]
                cf.extpos.send_extpose(*s["pos"], x, y, z, w)
                time.sleep(0.01)
        streamer = threading.Thread(target=stream, daemon=True)
        streamer.start()
        try:
            reset_estimator(scf)
            est = fleet.log_values(0)
            assert est["stateEstimate.x"] == pytest.approx(fleet.state(0)["pos"][0], abs=0.01)
            cf.supervisor.send_arming_request(True)
            x0, y0, _ = fleet.state(0)["pos"]
            cf.high_level_commander.takeoff(0.6, 1.5)
            time.sleep(2.0)
            cf.high_level_commander.go_to(x0 - 0.4, y0, 0.6, 0.0, 1.5)
            time.sleep(2.0)
            assert np.linalg.norm(fleet.state(0)["pos"] - [x0 - 0.4, y0, 0.6]) < 0.1
            cf.high_level_commander.land(0.0, 1.5)
            time.sleep(2.0)
            assert fleet.state(0)["pos"][2] < 0.02 and fleet.status(0)["thrust"] == fleet.idle_thrust(0)
        finally:
            stop.set()
            streamer.join()
        var0 = fleet.log_values(0)["kalman.varX"]
        time.sleep(0.5)
        assert fleet.log_values(0)["kalman.varX"] > 10 * var0          # no more external position
