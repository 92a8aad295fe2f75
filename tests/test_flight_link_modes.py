"""CflibLink's firmware-mode calls (pose stream, high-level commander, notify-stop, status) and the
pre-flight checks through the real cflib client over UDP against simulated Crazyflies, real time."""

import time

import numpy as np
import pytest

pytest.importorskip("cflib")

from cfrace.flight.link.crazyflie import CflibLink  # noqa: E402
from cfrace.flight.safety.preflight import PreflightConfig, run_checks  # noqa: E402
from cfrace.simcf.firmware import SimFleet  # noqa: E402
from cfrace.simcf.server import SimCrazyflieServer  # noqa: E402


def test_pose_stream_take_off_and_land_through_cflib_link():
    fleet = SimFleet("lemniscate", "cf21bl", 1, arming_required=True, decks=())
    with SimCrazyflieServer(fleet, base_port=0) as server:
        link = CflibLink(server.uris[0])
        link.connect(5.0)
        try:
            st = link.read_status()
            assert st["protocol"] == 12 and 3.9 < st["vbat"] < 4.2
            link.setup()                                   # armed, rate mode, unlocked
            x0, y0, _ = fleet.state(0)["pos"]

            def stream(seconds):
                t_end = time.monotonic() + seconds
                while time.monotonic() < t_end:
                    pos, quat = fleet.poses()[1]["cf1"]
                    link.send_pose(pos, quat)
                    time.sleep(0.01)
            stream(0.3)
            assert np.linalg.norm(fleet.log_values(0)["stateEstimate.x"] - x0) < 0.01
            # setup's zero-thrust unlock is a low-level setpoint: its priority blocks the high-level
            # commander until notify-stop (the firmware's rule)
            link.high_level("takeoff", height=0.5, yaw=None, duration=1.5)
            stream(0.3)
            assert fleet.state(0)["pos"][2] < 0.03
            link.notify_stop()
            link.high_level("takeoff", height=0.5, yaw=None, duration=1.5)
            stream(2.0)
            assert np.linalg.norm(fleet.state(0)["pos"] - [x0, y0, 0.5]) < 0.1
            for _ in range(20):                            # low-level takes over, then hands back
                link.send(0.0, 0.0, 0.0, 30000)
                time.sleep(0.01)
            assert fleet.status(0)["setpoint_source"] == "legacy"
            link.high_level("go_to", x=x0, y=y0, z=0.5, yaw=0.0, duration=1.0)
            link.notify_stop()
            stream(1.5)
            assert fleet.status(0)["setpoint_source"] == "high-level"
            assert np.linalg.norm(fleet.state(0)["pos"] - [x0, y0, 0.5]) < 0.1
            link.high_level("land", height=-0.05, yaw=None, duration=1.5)
            stream(2.0)
            assert fleet.state(0)["pos"][2] < 0.02 and fleet.status(0)["thrust"] == 0.0
            assert not fleet.status(0)["crashed"]
        finally:
            link.close()


def test_preflight_checks_through_cflib_in_real_time():
    fleet = SimFleet("lemniscate", "cf21bl", 2, arming_required=True)
    with SimCrazyflieServer(fleet, base_port=0) as server:
        links = [CflibLink(u) for u in server.uris]
        try:
            for link in links:
                link.connect(5.0)
            # a shared, loaded machine: the latency limit is the loop's timeout here, not a radio's
            checks = run_checks(links, ["cf2", "cf1"], fleet.profile, lambda: fleet.poses()[1], time.sleep,
                                PreflightConfig(max_latency_ms=500.0))
        finally:
            for link in links:
                link.close()
    assert [c.name for c in checks if not c.ok] == ["body", "body"], [c.line() for c in checks]
    assert "'cf1' rose most" in checks[6].detail
