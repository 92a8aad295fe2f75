"""Drones that raced close together land apart: a braking drone keeps away from the other flying
drones (landing.separation_accel), and a drone just ahead of one that flies on through its gate after
the race's end flies on with it (failsafe.fly_on_together) instead of braking in front of it."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from cfrace.drone import load_profile
from cfrace.flight.config import SafetyConfig
from cfrace.flight.landing.descent import LandingSetup, separation_accel
from cfrace.flight.safety.check import Fence
from cfrace.flight.safety.failsafe import SoftState, fly_on_together, flying_others
from cfrace.simcf.firmware import SimFleet
from cfrace.track import load_track
from test_flight_landing import rate_setpoint


def test_separation_pushes_apart_along_the_line_between_drones_and_is_bounded():
    me, other = np.array([0.0, 0.0, 1.0]), np.array([0.13, 0.0, 1.0])
    still = np.zeros(3)
    a = separation_accel(me, still, [(other, still)], 0.5, 40.0, 6.0, 8.0)
    assert a[0] == pytest.approx(-8.0) and a[1] == a[2] == 0.0                 # 40 * 0.37 = 14.8, at most 8
    a = separation_accel(me, still, [(np.array([0.45, 0.0, 1.0]), still)], 0.5, 40.0, 6.0, 8.0)
    assert a[0] == pytest.approx(-40.0 * 0.05)                                # spring only
    closing = separation_accel(me, still, [(np.array([0.45, 0.0, 1.0]), np.array([-0.5, 0.0, 0.0]))],
                               0.5, 40.0, 6.0, 8.0)
    assert closing[0] == pytest.approx(-40.0 * 0.05 - 6.0 * 0.5)               # plus the damper
    assert not separation_accel(me, still, [(np.array([0.0, 0.6, 1.0]), still)], 0.5, 40.0, 6.0, 8.0).any()
    # one drone on each side: the pushes cancel
    both = separation_accel(me, still, [(other, still), (np.array([-0.13, 0.0, 1.0]), still)], 0.5, 40.0, 6.0, 8.0)
    assert np.allclose(both, 0.0)


def test_the_push_is_not_swallowed_by_the_braking_at_speed():
    """At 6 m/s the braking alone asks for 36 m/s^2, capped at 12: the push comes first, so a drone
    closing in from behind makes the one ahead brake less, and one beside tilts it sideways."""
    setup = LandingSetup.for_race(load_track("complex"), load_profile("cf2x_paper"))
    pos, vel, level = np.array([0.0, 0.0, 1.0]), np.array([6.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0, 0.0])

    def command(near):
        brake = type(setup.brake)(**{**setup.brake.__dict__, "hold_z": 1.0})
        return brake.command(pos, vel, level, near)

    alone = command(())
    behind = command([(pos - [0.2, 0.0, 0.0], vel + [2.0, 0.0, 0.0])])
    beside = command([(pos + [0.0, 0.2, 0.0], vel)])
    far = command([(pos + [0.0, 0.6, 0.0], vel)])
    assert far[0].tolist() == alone[0].tolist() and far[1] == alone[1]
    assert behind[0][1] > alone[0][1]           # pitches forward, not back: away from the one closing in behind
    assert beside[0][0] > alone[0][0] + 1.0     # rolls away from the one on its left (+y)


def test_the_push_comes_from_the_other_flying_drones_only():
    def drone(stopped=False):
        return SimpleNamespace(stopped=stopped)

    def est(x, valid=True):
        return SimpleNamespace(pos=np.array([x, 0.0, 1.0]), vel=np.zeros(3), valid=valid)

    drones, ests = [drone(), drone(), drone(stopped=True), drone()], [est(0.0), est(0.1), est(0.2), est(5.0, False)]
    others = flying_others(0, drones, ests)
    assert len(others) == 1 and others[0][0][0] == 0.1            # not itself, the stopped, the invalid
    assert flying_others(0, drones, [est(0.0, False)] + ests[1:]) == []   # its own pose held: no push


def _brake_side_by_side(profile: str, keep_apart: bool) -> dict:
    """Two simulated Crazyflies flying at 6 m/s, 0.131 m apart (in contact, 2 radii = 0.13 m) and
    closing in at 0.2 m/s, as two drones that raced wing to wing; the left one starts braking 0.03 s
    before the right one. Each brakes with the flight loop's brake; keep_apart: told of the other one."""
    track = load_track("complex")
    fleet = SimFleet(track, profile, 2, arming_required=True, decks=())
    yaw = -math.pi / 2
    quat = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
    for i, x in enumerate((-0.0655, 0.0655)):
        fleet.arm(i, True)
        for name in ("flightmode.stabModeRoll", "flightmode.stabModePitch"):
            fleet.set_param(i, name, 0)
        fleet.handle_setpoint(i, 0, 0, 0, 0)                                      # unlock
        fleet.teleport(i, (x, 2.0, 1.2), (0.1 if i == 0 else -0.1, -6.0, 0.0), quat)
    setup = LandingSetup.for_race(track, fleet.profile)
    brakes = [type(setup.brake)(**{**setup.brake.__dict__, "hold_z": None}) for _ in range(2)]
    t = 0.0
    while t < 1.2 and not any(fleet.status(i)["crashed"] for i in range(2)):
        states = [fleet.state(i) for i in range(2)]
        for i, s in enumerate(states):
            fleet.external_position(i, s["pos"])
            o = states[1 - i]
            if i == 1 and t < 0.03:                      # still racing: the attitude it raced with
                rate_setpoint(fleet, i, (0.0, 0.0, 0.0), 0.9 * fleet.profile.mass * 9.81)
                continue
            near = [(o["pos"], o["vel"])] if keep_apart else ()
            rates, thrust = brakes[i].command(s["pos"], s["vel"], s["quat"], near)
            rate_setpoint(fleet, i, rates, thrust)
        fleet.advance(0.01)
        t += 0.01
    states = [fleet.state(i) for i in range(2)]
    return {"crashed": [fleet.status(i)["crashed"] for i in range(2)],
            "reasons": [fleet.status(i)["crash_reason"] for i in range(2)],
            "apart_m": float(np.linalg.norm(states[0]["pos"] - states[1]["pos"])),
            "speed": max(float(np.linalg.norm(s["vel"])) for s in states)}


@pytest.mark.slow
@pytest.mark.parametrize("profile", ["cf2x_paper", "cf21bl"])
def test_drones_braking_in_contact_part_before_the_contact_crashes_them(profile):
    """The 8-drone race end at 2.0 s on the complex track (studies/flight/flight_swarm_landings.md, "Race ends
    in a field"): drones braking in contact crashed once the contact had lasted 0.3 s. Told of each other,
    they part."""
    alone = _brake_side_by_side(profile, keep_apart=False)
    assert alone["crashed"] == [True, True] and alone["reasons"] == ["long_contact"] * 2, alone   # the case
    apart = _brake_side_by_side(profile, keep_apart=True)
    assert apart["crashed"] == [False, False] and apart["apart_m"] > 0.3 and apart["speed"] < 0.5, apart


def test_a_drone_just_ahead_of_one_that_flies_through_flies_on_with_it():
    est = lambda x, valid=True: SimpleNamespace(pos=np.array([x, 0.0, 1.0]), vel=np.array([5.0, 0.0, 0.0]),
                                                valid=valid)      # noqa: E731
    # all flying +x: 0 at the back, then 0.3 m, 0.6 m ahead (a chain), 2 m ahead, one invalid
    ests = [est(0.0), est(0.3), est(0.6), est(2.0), est(0.4, valid=False)]
    assert fly_on_together([0, 1, 2, 3, 4], {0}, ests, 0.5) == {0, 1, 2}
    assert fly_on_together([0, 1, 2, 3, 4], set(), ests, 0.5) == set()
    assert fly_on_together([0, 1, 2, 3], {2}, ests, 0.5) == {2}                # behind it: they brake
    off = lambda x, y: SimpleNamespace(pos=np.array([x, y, 1.0]), vel=np.array([5.0, 0.0, 0.0]), valid=True)  # noqa: E731
    assert fly_on_together([0, 1], {0}, [est(0.0), off(0.0, 0.2)], 0.5) == {0}         # beside it
    assert fly_on_together([0, 1], {0}, [est(0.0), off(0.3, 0.3)], 0.5) == {0}         # ahead, off its line
    assert fly_on_together([0, 1], {0}, [est(0.0), off(0.3, 0.2)], 0.5) == {0, 1}      # in its way
    towards = SimpleNamespace(pos=np.array([0.3, 0.0, 1.0]), vel=np.array([-5.0, 0.0, 0.0]), valid=True)
    assert fly_on_together([0, 1], {0}, [est(0.0), towards], 0.5) == {0}              # head-on: it brakes


def test_after_the_race_a_drone_ahead_of_one_that_flies_through_does_not_brake_in_front_of_it():
    """SoftState.land_after_race with a pack: the last drone's braking would take it into its gate
    (it flies through), the drone 0.2 m ahead of it flies on with it, a drone far away lands at once;
    once the last one is through both land in the same tick."""
    setup = LandingSetup.for_race(load_track("lemniscate"), load_profile("cf2x_paper"))
    fence = Fence.from_track(setup.track, SafetyConfig().geofence_margin_m)

    def drone(name):
        return SimpleNamespace(stopped=False, landing=None, frozen_pos=None, name=name, body=name, landing_result=None)

    def est(pos, vel):
        return SimpleNamespace(pos=np.array(pos, float), vel=np.array(vel, float), valid=True)

    from test_flight_landing import RACE_END_STATE
    last = np.array(RACE_END_STATE["pos"], float)
    ahead = last + 0.2 * np.array(RACE_END_STATE["vel"]) / np.linalg.norm(RACE_END_STATE["vel"])
    drones = [drone("a"), drone("b"), drone("c")]
    # the leader's own gate is the one behind it (index 0): alone, it would land at once
    ests = [est(last, RACE_END_STATE["vel"]), est(ahead, RACE_END_STATE["vel"]), est((0.0, 6.5, 1.0), (0, 4, 0))]
    soft = SoftState(3)
    soft.land_after_race(drones, ests, 3.71, 3.71, [5, 0, 0], fence, setup)
    assert drones[0].landing is None and drones[1].landing is None and drones[2].landing is not None
    ests[:2] = [est((-2.3, 3.2, 0.8), (1.0, -2.0, 0.0)), est((-2.1, 3.1, 0.8), (1.0, -2.0, 0.0))]   # through, turning
    soft.land_after_race(drones, ests, 3.95, 3.71, [0, 0, 0], fence, setup)
    assert drones[0].landing is not None and drones[1].landing is not None


@pytest.mark.slow
def test_a_field_that_raced_in_a_pack_lands_without_a_crash():
    """The 8-drone race of studies/flight/flight_swarm_landings.md, "Race ends in a field", ended at 2.0 s through
    the whole flight stack (lockstep): six drones race in a column, 0.13 m apart (in contact) when the race
    ends. Before the separation push and the chain of fly-through, three of them crashed in their
    landings (two in contact while braking, one run into from behind); now every one lands.
    d4 flies at low thrust (accelerometer body z below 0.5 g) from 1.84 s and is knocked by d2
    at 2.11 s (-0.43 g over 10 ms): the firmware's supervisor reads that knock through the 30 Hz
    low-pass at its 25 Hz tick (-0.15 g at 2.12 s, above the -0.2 g of its upside-down rule), so d4
    is not locked in the air as it was while the simulated supervisor read the raw value every 10 ms."""
    from cfrace.flight.config import FlightConfig
    from cfrace.rehearsal.dryrun import dry_run
    cfg = FlightConfig(track="complex", ego="ours", opp="ds", policies=("ours", "ds") * 4, profile="cf2x_paper",
                       laps=3, quiet=True, timeout_s=2.0)
    r = dry_run(cfg, lockstep=True).to_json()
    landing = [d for d in r["drones"] if d["landing"] is not None]
    assert len(landing) == 6, [(d["name"], d["stop_kind"]) for d in r["drones"]]   # d7, d8 never took off
    assert all(d["stop_kind"] == "landed" and d["landing"]["down"] for d in landing), r["landings"]
    assert not [f for f in r["drones_final"] if f["crashed"]] and not r["separation_at_stop"]
    assert not [e for e in r["safety_events"] if e["t"] >= 2.0 and (e["action"] != "none" or e["kind"] == "pose_outlier")]


@pytest.mark.slow
def test_eight_shipped_drones_race_from_a_hover_start():
    """From the ground, the last row of the 8-drone grid (2.1 m before gate 0) never lifts off (the
    race end above: d7, d8 stopped by the floor rule at 1 s); with --start hover the firmware takes
    every drone to its slot first, and all eight race through gates."""
    from cfrace.flight.config import FlightConfig
    from cfrace.rehearsal.dryrun import dry_run
    cfg = FlightConfig(track="complex", ego="ours", opp="ds", policies=("ours", "ds") * 4, profile="cf2x_paper",
                       laps=3, quiet=True, timeout_s=1.6, start="hover")
    r = dry_run(cfg, lockstep=True).to_json()
    assert max(r["hover_start"]["hold_error_m"]) <= 0.1
    assert all(d["gates_passed"] >= 1 for d in r["drones"]), [(d["name"], d["gates_passed"]) for d in r["drones"]]
    # the floor rule stops none that flies (two that meet in the pack and fall, a crash on contact,
    # are the race's chaos: each policy sees one opponent, and whether two meet depends on every rounding)
    met = {d["name"] for d, f in zip(r["drones"], r["drones_final"]) if f["crash_reason"] == "long_contact"}
    assert len(met) <= 2 and not [e for e in r["safety_events"] if e["kind"] == "floor" and e["drone"] not in met]
