"""The supervisor's clocks through the REAL cflib client (crazyflie-firmware supervisor.c:
isFlyingCheck's 2 s hysteresis, supervisorIsPreflightTimeout, supervisorIsLandingTimeout,
isTumbledCheck; supervisor_state_machine.c for what each leads to)."""

import time

import numpy as np
import pytest

cflib = pytest.importorskip("cflib")
import cflib.crtp  # noqa: E402

from cfrace.simcf.firmware import SimFleet  # noqa: E402
from cfrace.simcf.supervisor import AccelerometerFilter, SupervisorClock, supervisor_tick  # noqa: E402
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
    # reads, or one flying at low thrust (body z below 0.5 g) for a second
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
        assert float(cf.param.get_value("supervisor.crashDetectGs")) == 0.0     # the firmware's default: off
        cf.param.set_value("supervisor.crashDetectGs", "4.0")
        assert wait_for(lambda: fleet.get_param(0, "supervisor.crashDetectGs") == 4.0)


def _sine_gain(hz: float) -> float:
    """Peak output of the accelerometer filter for a unit sine on z, after 0.5 s of settling."""
    f = AccelerometerFilter()
    out = [f.run((0.0, 0.0, np.sin(2.0 * np.pi * hz * k / 1000.0)), 1, 1)[2] for k in range(1000)]
    return max(abs(v) for v in out[500:])


def test_the_accelerometer_reading_is_the_firmwares_30_hz_low_pass():
    # sensors_bmi088_bmp3xx.c: filter.c's 2nd-order Butterworth at 30 Hz on the 1 kHz samples
    assert _sine_gain(30.0) == pytest.approx(2 ** -0.5, abs=0.01)     # -3 dB at the cutoff
    assert _sine_gain(5.0) > 0.98 and _sine_gain(200.0) < 0.05
    f = AccelerometerFilter()
    assert f.run((0.1, -0.2, 1.0), 5, 5) == pytest.approx((0.1, -0.2, 1.0))   # settled on its first sample


def test_a_knock_while_flying_at_low_thrust_reaches_the_supervisor_low_passed():
    """d4's knock in the 8-drone pack (tests/test_flight_landing_pack.py): 0.3 s at 0.37 g, then
    -0.43 g for 10 ms. Raw, that reading is upside down (below -0.2 g) after more than 0.1 s tilted
    and locks the drone; through the filter it reads -0.15 g at the knock's end, and dips below
    -0.2 g for a few ms only, so one 25 Hz tick in several falls on it."""
    f, c = AccelerometerFilter(), SupervisorClock()
    f.run((0.0, 0.0, 0.37), 300)
    assert not c.tumbled(0.0, f.reading)                                # tilted: its clock starts
    knock = f.run((0.0, 0.0, -0.43), 10, 10)
    assert -0.2 < knock[2] < 0.0 and not c.tumbled(0.31, knock)
    after = [f.run((0.0, 0.0, 0.23), 1, 1)[2] for _ in range(20)]
    below = [v for v in after if v < -0.2]
    assert 0 < len(below) < 10                                           # ms below -0.2 g
    raw = SupervisorClock()
    assert not raw.tumbled(0.0, (0.0, 0.0, 0.37))
    assert raw.tumbled(0.31, (0.0, 0.0, -0.43))                         # what the raw reading did


def test_the_supervisor_runs_on_every_40th_tick_of_the_stabilizer_loop():
    assert supervisor_tick(0, 10) is None and supervisor_tick(30, 10) == 10 and supervisor_tick(36, 10) == 4
    assert supervisor_tick(38, 2) == 2 and supervisor_tick(40, 10) is None
    fleet = SimFleet("lemniscate", "cf2x_paper", 1, arming_required=True)
    fleet.set_param(0, "supervisor.prefltTimeout", 100)
    fleet.arm(0, True)
    fleet.advance(0.11)                                   # 10 ms past the timeout, before the tick at 120 ms
    assert fleet.status(0)["armed"]
    fleet.advance(0.02)
    assert not fleet.status(0)["armed"]                   # disarmed at the 25 Hz tick after the timeout


def _into_the_floor(crash_gs: float) -> tuple[dict, list]:
    """A hovering-thrust drone 0.3 m up, falling at 1.5 m/s onto the floor, crashDetectGs set."""
    from test_flight_landing import rate_setpoint

    fleet = SimFleet("lemniscate", "cf2x_paper", 1, arming_required=False, decks=())
    for name, value in (("supervisor.crashDetectGs", crash_gs), ("flightmode.stabModeRoll", 0),
                        ("flightmode.stabModePitch", 0)):
        fleet.set_param(0, name, value)
    fleet.handle_setpoint(0, 0, 0, 0, 0)
    fleet.teleport(0, (0.0, 5.0, 0.3), (0.0, 0.0, -1.5))
    for _ in range(60):
        rate_setpoint(fleet, 0, (0.0, 0.0, 0.0), fleet.profile.weight)
        fleet.advance(0.01)
    return fleet.status(0), fleet._fw[0].events


def test_crash_detection_reads_the_impact_when_crashdetectgs_is_set():
    # isTumbledCheck: | |acc| - 1 g | above supervisor.crashDetectGs counts as tumbled; 0 (default): off
    status, events = _into_the_floor(0.0)
    assert not status["emergency_stopped"] and not [e for e in events if "crash" in e]
    status, events = _into_the_floor(4.0)
    assert status["supervisor_crashed"] and not status["emergency_stopped"] and status["thrust"] == 0.0
    crash = [e for e in events if e.startswith("SUP: crash detected @ ")]
    assert len(crash) == 1 and crash[0].endswith("Gs (max 4.00)")
    assert float(crash[0].split("@ ")[1].split(" ")[0]) > 5.0


def test_a_drone_that_tumbles_in_flight_is_crashed_until_a_recovery_request_through_cflib():
    """supervisor_state_machine.c: Flying -> Crashed on a tumble (motors off, disarmed; not Locked,
    no reboot needed); cflib's send_crash_recovery_request leaves it once it no longer reads
    tumbled, and it can be armed again."""
    from test_flight_landing import rate_setpoint
    fleet = SimFleet("lemniscate", "cf21bl", 1, arming_required=True, decks=())
    for name, value in (("supervisor.crashDetectGs", 4.0), ("flightmode.stabModeRoll", 0),
                        ("flightmode.stabModePitch", 0)):
        fleet.set_param(0, name, value)
    # the fall onto the floor in simulated time (served, the fleet runs on the wall clock: the impact's
    # filtered reading would then depend on how the host's scheduling steps it)
    fleet.arm(0, True)
    fleet.handle_setpoint(0, 0, 0, 0, 0)
    fleet.teleport(0, (0.0, 5.0, 0.3), (0.0, 0.0, -1.5))
    for _ in range(60):
        rate_setpoint(fleet, 0, (0.0, 0.0, 0.0), fleet.profile.weight)
        fleet.advance(0.01)
    assert fleet.status(0)["supervisor_crashed"]
    with served(fleet) as cf:
        assert wait_for(lambda: cf.supervisor.is_crashed)
        assert not cf.supervisor.is_locked and not cf.supervisor.can_fly and not cf.supervisor.is_armed
        assert fleet.status(0)["thrust"] == 0.0
        cf.supervisor.send_crash_recovery_request()
        assert wait_for(lambda: not fleet.status(0)["supervisor_crashed"])
        assert wait_for(lambda: cf.supervisor.can_be_armed)
        cf.supervisor.send_arming_request(True)
        assert wait_for(lambda: fleet.status(0)["armed"])
