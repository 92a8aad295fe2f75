"""External pose fusion through the REAL cflib client (crazyflie-firmware crtp_localization_service.c,
extPoseHandler / extPositionPackedHandler / extPosePackedHandler; kalman_core.c, kalmanCoreUpdateWithPose;
estimator_kalman.c, resetEstimation): the extpose quaternion steers the attitude estimate, so a
swapped quaternion order or a wrong kalman.initialYaw with position-only mocap makes the drone
misbehave as a real one does; packed positions and poses reach the drone their id names."""

import math
import struct
import time

import numpy as np
import pytest

cflib = pytest.importorskip("cflib")
import cflib.crtp  # noqa: E402
from cflib.crazyflie.log import LogConfig  # noqa: E402
from cflib.crazyflie.syncLogger import SyncLogger  # noqa: E402
from cflib.crtp.crtpstack import CRTPPacket  # noqa: E402

from cfrace.simcf.firmware import SimFleet, quat_to_euler  # noqa: E402
from cfrace.simcf.server import SimCrazyflieServer  # noqa: E402
from cflibtools import connect, wait_for  # noqa: E402

cflib.crtp.init_drivers()

Z = 0.6   #: m, hover height


def fly(cf, fleet, seconds, send_pose):
    """Position setpoints at the start point and Z for `seconds`, send_pose(cf, pos, quat) each 10 ms;
    -> (largest distance from the hover point m, largest tilt deg, largest |estimated - true yaw| deg)."""
    x0, y0 = fleet.state(0)["pos"][:2]
    goal = np.array([x0, y0, Z])
    far = tilt = yaw_err = 0.0
    t_end = time.monotonic() + seconds
    t_half = time.monotonic() + seconds / 2.0
    while time.monotonic() < t_end:
        s = fleet.state(0)
        send_pose(cf, s["pos"], s["quat"])
        cf.commander.send_position_setpoint(*goal, 0.0)
        if time.monotonic() > t_half:      # after take-off
            far = max(far, float(np.linalg.norm(s["pos"] - goal)))
            w, x, y, z = s["quat"]
            tilt = max(tilt, math.degrees(math.acos(max(-1.0, min(1.0, 1.0 - 2.0 * (x * x + y * y))))))
            est_yaw = fleet.log_values(0)["stateEstimate.yaw"]
            d = (est_yaw - math.degrees(quat_to_euler(s["quat"])[2]) + 180.0) % 360.0 - 180.0
            yaw_err = max(yaw_err, abs(d))
        time.sleep(0.01)
    return far, tilt, yaw_err


def extpose_xyzw(cf, pos, q):          # the right order: cflib wants qx, qy, qz, qw
    w, x, y, z = q
    cf.extpos.send_extpose(*pos, x, y, z, w)


def extpose_wxyz(cf, pos, q):          # the classic mistake: w first
    cf.extpos.send_extpose(*pos, *q)


def extpos_only(cf, pos, q):
    cf.extpos.send_extpos(*pos)


def run(send_pose, initial_yaw=None, seconds=4.0):
    fleet = SimFleet("lemniscate", "cf2x_paper", 1, arming_required=False, decks=())
    with SimCrazyflieServer(fleet, base_port=0) as server, connect(server.uris[0]) as scf:
        cf = scf.cf
        scf.wait_for_params()
        if initial_yaw is not None:
            cf.param.set_value("kalman.initialYaw", f"{initial_yaw(fleet._start_yaw):.4f}")
            cf.param.set_value("kalman.resetEstimation", "1")
            assert wait_for(lambda: fleet.get_param(0, "kalman.resetEstimation") == 0
                            and abs(fleet.get_param(0, "kalman.initialYaw") - initial_yaw(fleet._start_yaw)) < 1e-3)
        return fly(cf, fleet, seconds, send_pose)


def test_extpose_in_the_firmware_order_hovers_and_the_estimate_takes_the_mocap_yaw():
    # the start yaw is not kalman.initialYaw (0): the quaternion must bring the estimate round
    far, tilt, yaw_err = run(extpose_xyzw)
    assert far < 0.1 and tilt < 10.0 and yaw_err < 2.0


def test_swapped_quaternion_order_makes_the_drone_misbehave():
    far, tilt, _ = run(extpose_wxyz, seconds=3.0)
    assert far > 0.4 or tilt > 60.0


def test_position_only_mocap_needs_the_right_initial_yaw():
    far, tilt, yaw_err = run(extpos_only, initial_yaw=lambda true: true)
    assert far < 0.15 and yaw_err < 2.0
    far, _, yaw_err = run(extpos_only, initial_yaw=lambda true: true + 2.0)   # 115 deg off
    assert yaw_err > 90.0 and far > 0.4     # the position loop pushes the wrong way: it flies off


def quat_compress(q_wxyz) -> int:
    """The firmware's 32-bit 'smallest three' quaternion (quatcompress.h), order x y z w."""
    w, x, y, z = q_wxyz
    q = [x, y, z, w]
    big = max(range(4), key=lambda k: abs(q[k]))
    if q[big] < 0:
        q = [-v for v in q]
    comp = big
    for k in range(4):
        if k != big:
            mag = int(((1 << 9) - 1) * abs(q[k]) * math.sqrt(2.0) + 0.5)
            comp = (comp << 10) | (int(q[k] < 0) << 9) | mag
    return comp


def send_raw(cf, channel, data):
    pk = CRTPPacket()
    pk.port, pk.channel, pk.data = 6, channel, data
    cf.send_packet(pk)


def test_packed_positions_and_poses_reach_the_drone_their_id_names():
    fleet = SimFleet("lemniscate", "cf2x_paper", 2, arming_required=False, decks=())
    assert [fleet.radio_id(i) for i in range(2)] == [1, 2]
    yaw = 0.7
    q = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
    with SimCrazyflieServer(fleet, base_port=0) as server, connect(server.uris[1]) as scf:
        cf = scf.cf
        scf.wait_for_params()
        items = struct.pack("<Bhhh", 1, 5000, 5000, 5000) + struct.pack("<Bhhh", 2, 1234, -2345, 456)
        pose = struct.pack("<BhhhI", 1, 0, 0, 0, 0) + struct.pack("<BhhhI", 2, 1234, -2345, 456, quat_compress(q))
        for _ in range(50):
            send_raw(cf, 2, items)
            send_raw(cf, 1, bytes([9]) + pose)
            time.sleep(0.01)
        assert wait_for(lambda: abs(fleet.log_values(1)["stateEstimate.yaw"] - math.degrees(yaw)) < 1.0)
        est = fleet._fw[1].estimator
        assert est.pos == pytest.approx([1.234, -2.345, 0.456], abs=0.01)
        # drone 1 (id 2) ignored the items for id 1; drone 0 (id 1) got nothing: it is on another link
        assert fleet._fw[0].estimator.updates == 0


def test_a_nan_quaternion_is_dropped_with_one_console_line_and_the_position_still_used():
    fleet = SimFleet("lemniscate", "cf2x_paper", 1, arming_required=False, decks=())
    with SimCrazyflieServer(fleet, base_port=0) as server, connect(server.uris[0]) as scf:
        cf = scf.cf
        lines = []
        cf.console.receivedChar.add_callback(lines.append)
        scf.wait_for_params()
        for _ in range(30):
            cf.extpos.send_extpose(1.0, 2.0, 0.5, float("nan"), 0.0, 0.0, 1.0)
            time.sleep(0.01)
        assert wait_for(lambda: "invalid quaternion" in "".join(lines))
        time.sleep(0.3)
        assert "".join(lines).count("invalid quaternion") == 1
        assert fleet._fw[0].estimator.pos == pytest.approx([1.0, 2.0, 0.5], abs=0.01)
        assert np.all(np.isfinite(fleet._fw[0].estimator.q_err))


LOC_LOGS = (("locSrv.x", "locSrv.y", "locSrv.z", "locSrv.qx", "locSrv.qy", "locSrv.qz"),   # 26 bytes a block
            ("locSrv.qw", "ext_pos.X", "ext_pos.Y", "ext_pos.Z", "locSrvZ.tick"))


def read_logs(cf):
    """One sample of every LOC_LOGS variable, logged through cflib."""
    out = {}
    for k, names in enumerate(LOC_LOGS):
        conf = LogConfig(name=f"loc{k}", period_in_ms=10)
        for name in names:
            conf.add_variable(name, "uint16_t" if name.endswith("tick") else "float")
        with SyncLogger(cf, conf) as logger:
            for _, data, _ in logger:
                out.update(data)
                break
    return out


def test_locsrv_logs_and_params_are_the_last_external_pose_as_the_firmware_has_them():
    """crtp_localization_service.c: locSrv.x..qw the last pose (a position updates x y z and keeps the
    quaternion), ext_pos.X/Y/Z the last position (packed items for other drones too), locSrvZ.tick
    the ms tick of the last packet for this drone; the locSrv parameters with the firmware's defaults."""
    fleet = SimFleet("lemniscate", "cf2x_paper", 1, arming_required=False, decks=())
    with SimCrazyflieServer(fleet, base_port=0) as server, connect(server.uris[0]) as scf:
        cf = scf.cf
        scf.wait_for_params()
        assert float(cf.param.get_value("locSrv.extPosStdDev")) == pytest.approx(0.01)
        assert float(cf.param.get_value("locSrv.extQuatStdDev")) == pytest.approx(4.5e-3)
        assert [cf.param.get_value(f"locSrv.{n}") for n in ("enRangeStreamFP32", "enLhAngleStream", "enLhMtchStm",
                                                           "maxTimeLhMtchStm", "minBsLhMtchStm")] == ["0", "0", "0", "25", "2"]
        assert all(v == 0.0 for k, v in read_logs(cf).items())          # nothing received yet
        qz, qw = math.sin(0.35), math.cos(0.35)
        for _ in range(5):
            cf.extpos.send_extpose(1.0, 2.0, 0.5, 0.0, 0.0, qz, qw)
            time.sleep(0.01)
        logs = read_logs(cf)
        assert [logs[f"locSrv.{n}"] for n in ("x", "y", "z", "qx", "qy", "qz", "qw")] == pytest.approx(
            [1.0, 2.0, 0.5, 0.0, 0.0, qz, qw], abs=1e-6)
        assert [logs[f"ext_pos.{n}"] for n in "XYZ"] == [0.0, 0.0, 0.0]   # a pose is not a position
        tick = logs["locSrvZ.tick"]
        assert 0 < (int(fleet.time * 1000) - tick) % 65536 < 1000      # ms, within the last second
        for _ in range(5):
            cf.extpos.send_extpos(3.0, 4.0, 1.0)
            time.sleep(0.01)
        logs = read_logs(cf)
        assert [logs[f"locSrv.{n}"] for n in ("x", "y", "z", "qz", "qw")] == pytest.approx([3.0, 4.0, 1.0, qz, qw], abs=1e-6)
        assert [logs[f"ext_pos.{n}"] for n in "XYZ"] == pytest.approx([3.0, 4.0, 1.0], abs=1e-6)
        send_raw(cf, 1, bytes([9]) + struct.pack("<BhhhI", 7, -500, 600, 700, quat_compress((1.0, 0.0, 0.0, 0.0))))
        time.sleep(0.1)
        logs = read_logs(cf)
        assert [logs[f"ext_pos.{n}"] for n in "XYZ"] == pytest.approx([-0.5, 0.6, 0.7], abs=1e-6)   # a peer's
        assert [logs[f"locSrv.{n}"] for n in ("x", "y", "z")] == pytest.approx([3.0, 4.0, 1.0], abs=1e-6)
