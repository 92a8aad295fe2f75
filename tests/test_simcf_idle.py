"""The Crazyflie 2.1 Brushless's idle thrust through the REAL cflib client (crazyflie-firmware
power_distribution_quadrotor.c, powerDistributionCap; supervisor.c, supervisorAreMotorsAllowedToRun):
armed, its props spin at powerDist.idleThrust (7000 counts per motor) whatever the setpoint, and
lower commands are floored there; disarmed or stopped they do not spin."""

import time

import numpy as np
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


def test_the_flight_stack_warns_of_the_idle_floor_a_policy_did_not_train_with():
    """The shipped policies trained on cf2x_paper (no idle floor): raced on cf21bl, whose real
    drones floor every armed motor at 7000 counts, the start-up banner says so, once per policy."""
    from types import SimpleNamespace

    from cfrace.drone import load_profile
    from cfrace.flight.config import FlightConfig
    from cfrace.flight.setup import idle_floor_notes, resolve_race

    setup = resolve_race(FlightConfig(track="lemniscate", ego="ours", opp="ds", profile="cf21bl"))
    assert len(setup.notes) == 2 and all("7000 counts per motor" in n for n in setup.notes)
    assert setup.notes[0].startswith("ego: ours_lemniscate.onnx trained on cf2x_paper")
    assert resolve_race(FlightConfig(track="lemniscate", ego="ours", opp="ds", profile="cf2x_paper")).notes == ()
    spanned = SimpleNamespace(policy=SimpleNamespace(meta={"drone_profile": "cf2x_paper",
                                                           "drone_ranges": {"profiles": ["cf2x_paper", "cf21bl"]}}),
                              path=setup.policies[0].path)
    assert idle_floor_notes(load_profile("cf21bl"), {"ego": spanned}) == ()      # trained with the floor



def test_a_fleet_boots_with_the_brushless_idle_when_asked_and_keeps_it_across_a_reboot():
    from cfrace.errors import ConfigError

    fleet = SimFleet("lemniscate", "cf21bl", 1, arming_required=True, params={"powerDist.idleThrust": 7000})
    assert fleet.get_param(0, "powerDist.idleThrust") == 7000
    fleet.reboot(0)
    assert fleet.get_param(0, "powerDist.idleThrust") == 7000                 # the build's default
    with pytest.raises(ConfigError, match="'firmware.modified' is not a writable parameter"):
        SimFleet("lemniscate", "cf21bl", 1, params={"firmware.modified": 1})


@pytest.mark.slow
def test_the_dry_run_rehearses_the_brushless_idle_floor():
    """`cfrace sim dry-run --idle-thrust 7000`: the shipped DS policy (trained without a floor) dives
    on the lemniscate at its least thrust from about 3.4 s; with the floor its drone flies another line."""
    from cfrace.flight.config import FlightConfig
    from cfrace.rehearsal.dryrun import dry_run

    cfg = FlightConfig(track="lemniscate", ego="ours", opp="ds", profile="cf21bl", quiet=True, timeout_s=3.9,
                       landing=False)
    runs = [dry_run(cfg, lockstep=True, idle_thrust=idle).to_json() for idle in (None, 7000)]
    opp = [next(f for f in r["drones_final"] if f["body"] == "cf2")["pos"] for r in runs]
    assert np.linalg.norm(np.subtract(opp[0], opp[1])) > 0.05, opp
