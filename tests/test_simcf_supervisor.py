"""The supervisor's clocks through the REAL cflib client (crazyflie-firmware supervisor.c:
isFlyingCheck's 2 s hysteresis, supervisorIsPreflightTimeout, supervisorIsLandingTimeout,
isTumbledCheck; supervisor_state_machine.c for what each leads to)."""

import time

import numpy as np
import pytest

cflib = pytest.importorskip("cflib")
import cflib.crtp  # noqa: E402

from cfrace.simcf.firmware import SimFleet  # noqa: E402
from cfrace.simcf.supervisor import SupervisorClock  # noqa: E402
from cflibtools import served, wait_for  # noqa: E402

cflib.crtp.init_drivers()

LOCKED, ARMED, FLYING = 0x40, 0x02, 0x10


def hover(cf, fleet, seconds, z=0.5):
    x0, y0 = fleet.state(0)["pos"][:2]
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        cf.commander.send_position_setpoint(x0, y0, z, 0.0)
        time.sleep(0.01)


def stops_then_silence(stop_seconds):
    """Hover, then stop setpoints for stop_seconds, then nothing for 2.6 s: -> supervisor.info."""
    fleet = SimFleet("lemniscate", "cf2x_paper", 1, arming_required=False)
    with served(fleet) as cf:
        hover(cf, fleet, 2.0)
        assert fleet.supervisor_bitfield(0) & FLYING
        t_end = time.monotonic() + stop_seconds
        while time.monotonic() < t_end:
            cf.commander.send_stop_setpoint()
            time.sleep(0.01)
        time.sleep(2.6)
        return fleet.supervisor_bitfield(0)


def test_silence_right_after_the_motors_stop_locks_the_drone_as_the_2s_hysteresis_does():
    # 0.3 s of stop setpoints: still "flying" (motors above idle 0.3 s ago) when the watchdog's
    # level-out begins, so its 2 s timeout locks the drone
    assert stops_then_silence(0.3) & LOCKED
    # 2.5 s of stop setpoints: landed before the silence, no lock
    info = stops_then_silence(2.5)
    assert not info & LOCKED and not info & FLYING


def test_preflight_and_landing_timeouts_disarm():
    fleet = SimFleet("lemniscate", "cf2x_paper", 1, arming_required=True)
    with served(fleet) as cf:
        assert cf.param.get_value("supervisor.prefltTimeout") == "30000"
        assert cf.param.get_value("supervisor.landedTimeout") == "3000"
        cf.param.set_value("supervisor.prefltTimeout", "1000")
        cf.param.set_value("supervisor.landedTimeout", "500")
        assert wait_for(lambda: fleet.get_param(0, "supervisor.landedTimeout") == 500)
        cf.supervisor.send_arming_request(True)
        assert wait_for(lambda: fleet.supervisor_bitfield(0) & ARMED)
        t0 = time.monotonic()
        assert wait_for(lambda: not fleet.supervisor_bitfield(0) & ARMED, timeout=3.0)
        assert time.monotonic() - t0 > 0.8          # 1 s armed without flying
        # fly, land, stop: 2 s hysteresis + 0.5 s landed timeout -> disarmed
        cf.supervisor.send_arming_request(True)
        assert wait_for(lambda: fleet.supervisor_bitfield(0) & ARMED)
        hover(cf, fleet, 1.5)
        for _ in range(50):
            cf.commander.send_stop_setpoint()
            time.sleep(0.01)
        t0 = time.monotonic()
        assert fleet.supervisor_bitfield(0) & ARMED
        assert wait_for(lambda: not fleet.supervisor_bitfield(0) & ARMED, timeout=5.0)
        assert time.monotonic() - t0 > 1.5


def test_the_tumble_check_times_a_tilt_and_an_upside_down_and_free_fall_resets_it():
    # isTumbledCheck on the accelerometer (body frame, g): what a drone lying on its side or back
    # reads (in the air the thrust keeps body z positive, so a flying drone never reads tumbled)
    c = SupervisorClock()
    assert not any(c.tumbled(t, (0.0, 0.9, 0.3)) for t in np.arange(0.0, 0.99, 0.01))   # 70 deg, < 1 s
    assert c.tumbled(1.02, (0.0, 0.9, 0.3))
    assert not c.tumbled(1.03, (0.0, 0.0, 0.05))                                      # free fall resets
    assert not c.tumbled(1.04, (0.0, 0.0, -1.0)) and not c.tumbled(1.13, (0.0, 0.0, -1.0))
    assert c.tumbled(1.15, (0.0, 0.0, -1.0))                                          # upside down, 0.1 s
    assert not c.tumbled(1.16, (0.0, 0.0, 1.0))


def test_tmblchcken_is_a_parameter_of_the_supervisor():
    fleet = SimFleet("lemniscate", "cf2x_paper", 1, arming_required=False)
    with served(fleet) as cf:
        assert cf.param.get_value("supervisor.tmblChckEn") == "1"
        cf.param.set_value("supervisor.tmblChckEn", "0")
        assert wait_for(lambda: fleet.get_param(0, "supervisor.tmblChckEn") == 0)
