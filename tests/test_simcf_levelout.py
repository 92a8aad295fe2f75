"""The supervisor's level-out and watchdog lock through the REAL cflib client (crazyflie-firmware
src/modules/src/supervisor.c, supervisorOverrideSetpoint; supervisor_state_machine.c, transitionsFlying
and transitionsWarningLevelOut): 500 ms after the last setpoint x and y are disabled, roll and pitch
levelled, the yaw rate zeroed and z kept; 2 s after it, a flying drone locks until a reboot."""

import math
import time

import numpy as np
import pytest

cflib = pytest.importorskip("cflib")
import cflib.crtp  # noqa: E402

from cfrace.simcf.firmware import SimFleet  # noqa: E402
from cfrace.simcf.server import SimCrazyflieServer  # noqa: E402
from cflibtools import connect, wait_for  # noqa: E402

cflib.crtp.init_drivers()

Z = 0.6   #: m, hover height


def tilt_deg(quat) -> float:
    """Angle between the body z axis and the world z axis, deg."""
    w, x, y, z = quat
    return math.degrees(math.acos(max(-1.0, min(1.0, 1.0 - 2.0 * (x * x + y * y)))))


def hover_then_step(cf, fleet, x0, y0):
    """Position setpoints: hover at (x0, y0, Z) until settled, then (x0 + 1 m) for 0.15 s, then none."""
    t_end = time.monotonic() + 30.0
    settled = 0
    while settled < 100:                                     # 1 s within 5 cm, level
        cf.commander.send_position_setpoint(x0, y0, Z, 0.0)
        s = fleet.state(0)
        near = np.linalg.norm(s["pos"] - [x0, y0, Z]) < 0.05 and np.linalg.norm(s["vel"]) < 0.05
        settled = settled + 1 if near else 0
        assert time.monotonic() < t_end, "never settled at the hover point"
        time.sleep(0.01)
    for _ in range(15):
        cf.commander.send_position_setpoint(x0 + 1.0, y0, Z, 0.0)
        time.sleep(0.01)


def sample_until(fleet, age_end):
    """(setpoint age s, state, status) of drone 0 every ~10 ms until the setpoint age passes age_end."""
    rows = []
    t_end = time.monotonic() + 20.0
    while time.monotonic() < t_end:
        st = fleet.status(0)
        rows.append((st["setpoint_age"], fleet.state(0), st))
        if st["setpoint_age"] is not None and st["setpoint_age"] > age_end:
            return rows
        time.sleep(0.01)
    raise AssertionError("simulated time did not advance")


def test_level_out_disables_x_y_keeps_z_and_the_watchdog_locks_in_flight():
    fleet = SimFleet("lemniscate", "cf2x_paper", 1, arming_required=False)
    x0, y0 = fleet.state(0)["pos"][:2]
    with SimCrazyflieServer(fleet, base_port=0) as server, connect(server.uris[0]) as scf:
        cf = scf.cf
        scf.wait_for_params()
        hover_then_step(cf, fleet, x0, y0)
        rows = sample_until(fleet, 2.3)
        level = [(s, st) for age, s, st in rows if 0.8 <= age <= 1.9]
        assert len(level) >= 20 and all(st["watchdog"] == "level" for _, st in level)
        # x, y disabled and levelled: the drone coasts level (position control would pull it back
        # and decelerate toward x0 + 1 m at a tilt of several degrees)
        assert max(tilt_deg(s["quat"]) for s, _ in level) < 3.0
        vx = [s["vel"][0] for s, _ in level]
        span = level[-1][1]["setpoint_age"] - level[0][1]["setpoint_age"]
        # drag only (the profile's, about 0.25 m/s^2 at 1 m/s), no braking: the position controller
        # would stop the drone at x0 + 1 m, several m/s^2
        assert vx[0] > 0.3 and vx[-1] > 0.5 * vx[0] and (vx[0] - vx[-1]) / span < 0.5
        # z kept: still at the hover height
        assert all(abs(s["pos"][2] - Z) < 0.1 for s, _ in level)
        # 2 s: in flight the supervisor locks, reboot required; a zero-thrust setpoint does not unlock
        st = rows[-1][2]
        assert st["watchdog"] == "shutdown" and st["emergency_stopped"] and st["thrust"] == 0.0
        assert fleet.supervisor_bitfield(0) & 0x40
        for _ in range(10):
            cf.commander.send_setpoint(0, 0, 0, 0)
            cf.commander.send_position_setpoint(x0, y0, Z, 0.0)
            time.sleep(0.01)
        assert wait_for(lambda: fleet.status(0)["setpoints_received"] > 0)
        assert fleet.status(0)["thrust"] == 0.0
