"""The Crazyflie 2.1 Brushless's idle thrust through the REAL cflib client (crazyflie-firmware
power_distribution_quadrotor.c, powerDistributionCap; supervisor.c, supervisorAreMotorsAllowedToRun):
armed, its props spin at powerDist.idleThrust (7000 counts per motor) whatever the setpoint, and
lower commands are floored there; disarmed or stopped they do not spin."""

import time

import pytest

cflib = pytest.importorskip("cflib")
import cflib.crtp  # noqa: E402

from cfrace.simcf.firmware import SimFleet  # noqa: E402
from cflibtools import served, wait_for  # noqa: E402

cflib.crtp.init_drivers()


def test_armed_brushless_motors_idle_at_7000_counts_and_low_commands_are_floored():
    fleet = SimFleet("lemniscate", "cf21bl", 1, arming_required=True)
    with served(fleet) as cf:
        assert cf.param.get_value("powerDist.idleThrust") == "0"       # the simulator's default (docs/simcf.md)
        cf.param.set_value("powerDist.idleThrust", "7000")             # the Brushless firmware's own default
        assert wait_for(lambda: fleet.get_param(0, "powerDist.idleThrust") == 7000)
        assert fleet.status(0)["thrust"] == 0.0                       # disarmed: off
        cf.supervisor.send_arming_request(True)
        assert wait_for(lambda: fleet.status(0)["armed"])
        # armed, no setpoint yet: idle
        idle_n = float(fleet.profile.thrust_curve.to_newtons(7000))
        assert wait_for(lambda: fleet.status(0)["thrust"] == pytest.approx(idle_n))
        assert fleet.status(0)["thrust_counts"] == 7000
        # a legacy setpoint of 3000 counts (above the 1000-count cut, below idle): floored at idle
        cf.commander.send_setpoint(0.0, 0.0, 0.0, 0)
        for _ in range(20):
            cf.commander.send_setpoint(0.0, 0.0, 0.0, 3000)
            time.sleep(0.01)
        assert fleet.status(0)["thrust_counts"] == 7000
        assert fleet.state(0)["pos"][2] < 0.05                        # idle does not lift it
        # a command above idle passes unchanged
        for _ in range(5):
            cf.commander.send_setpoint(0.0, 0.0, 0.0, 9000)
            time.sleep(0.01)
        assert fleet.status(0)["thrust_counts"] == 9000
        cf.supervisor.send_arming_request(False)
        assert wait_for(lambda: fleet.status(0)["thrust"] == 0.0)


def test_the_crazyflie_2_1_has_no_idle_thrust():
    fleet = SimFleet("lemniscate", "cf2x_paper", 1, arming_required=False)
    assert fleet.get_param(0, "powerDist.idleThrust") == 0
    fleet.advance(0.1)
    assert fleet.status(0)["thrust"] == 0.0
