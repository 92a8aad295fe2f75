"""Landing spots, braking from race speed and the hand-over to the firmware's high-level commander."""

import math

import numpy as np
import pytest

from cfrace.flight.config import SafetyConfig
from cfrace.flight.landing.descent import BrakeController, LandingSetup, Touchdown, stopping_point
from cfrace.flight.safety.check import Fence
from cfrace.flight.landing.spots import (LandingConfig, candidate_spots, choose_landing_spots, gate_footprints, _obstacle_dist,
                                 _seg_point_dist)
from cfrace.flight.link.protocol import packet_values
from cfrace.simcf.firmware import SimFleet
from cfrace.track import load_track


def clear_of_everything(track, spot, cfg):
    a = track.arena
    assert a.x[0] + cfg.wall_margin_m - 1e-9 <= spot[0] <= a.x[1] - cfg.wall_margin_m + 1e-9
    assert a.y[0] + cfg.wall_margin_m - 1e-9 <= spot[1] <= a.y[1] - cfg.wall_margin_m + 1e-9
    for g0, g1 in gate_footprints(track):
        assert _seg_point_dist(g0, g1, np.asarray(spot)[None])[0] >= cfg.gate_clearance_m - 1e-9
    assert _obstacle_dist(track, np.asarray(spot)[None])[0] >= cfg.obstacle_clearance_m - 1e-9


def test_spots_are_free_near_the_stop_and_apart():
    track = load_track("lemniscate")
    cfg = LandingConfig()
    cand = candidate_spots(track, cfg)
    assert len(cand) > 100
    # both drones stopping at the same place just past gate 1 (inside its frame's clearance)
    stops = np.array([[0.2, 5.25], [0.3, 5.3]])
    spots = choose_landing_spots(track, stops, others=[[1.0, 4.0]], cfg=cfg)
    for s in spots:
        clear_of_everything(track, s, cfg)
        assert np.linalg.norm(s - [1.0, 4.0]) >= cfg.drone_separation_m
    assert np.linalg.norm(spots[0] - spots[1]) >= cfg.drone_separation_m
    assert np.linalg.norm(spots[0] - stops[0]) < 1.5 and np.linalg.norm(spots[1] - stops[1]) < 1.5
    with pytest.raises(ValueError, match="no free landing spot"):
        choose_landing_spots(track, stops, others=cand, cfg=cfg)


def test_a_spot_is_not_reached_through_a_gate_or_an_obstacle():
    track = load_track("lemniscate")
    # just before gate 0 (at x 1.5, y 3.5, its frame spans x 0.8-2.2): the nearest spots beyond the
    # frame must not be chosen by flying through it
    stop = np.array([1.5, 3.7])
    spot = choose_landing_spots(track, [stop])[0]
    g0, g1 = gate_footprints(track)[0]
    from cfrace.flight.landing.spots import _segments_cross
    assert not _segments_cross(stop, spot, g0, g1)


def test_stopping_point():
    assert stopping_point([0, 0, 1], [4.0, 0, 0], 8.0) == pytest.approx([1.0, 0.0, 1.0])


def rate_setpoint(fleet, i, rates_dps, thrust_n):
    """What the flight link sends: body rates and thrust counts, as the legacy packet."""
    counts = int(np.clip(fleet.profile.thrust_curve.to_counts(thrust_n), 1000, 60000))
    fleet.handle_setpoint(i, *packet_values(*rates_dps), counts)


@pytest.mark.parametrize("profile", ["cf2x_paper", "cf21bl"])
def test_brake_hand_over_and_land_from_race_speed(profile):
    """A drone crossing the lemniscate's finish (gate 5, 1.5 m before the arena's wall) at 5 m/s towards
    the wall: braked in rate mode from its state, then the high-level commander (go-to the spot,
    land), all on the simulated firmware. On the ground within 5 s, softly, on its spot, never out
    of the fence."""
    track = load_track("lemniscate")
    fleet = SimFleet(track, profile, 1, arming_required=True, decks=())
    fleet.arm(0, True)
    for name in ("flightmode.stabModeRoll", "flightmode.stabModePitch"):
        fleet.set_param(0, name, 0)
    fleet.handle_setpoint(0, 0, 0, 0, 0)                                   # unlock
    yaw = -math.pi / 2
    fleet.teleport(0, (-2.0, 3.4, 0.75), (0.0, -5.0, 0.0), (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)))
    prof = fleet.profile
    brake = LandingSetup.for_race(track, prof).brake       # what the flight loop brakes with
    cfg = LandingConfig()
    s = fleet.state(0)
    spot = choose_landing_spots(track, [stopping_point(s["pos"], s["vel"], brake.accel_max)], cfg=cfg)[0]
    clear_of_everything(track, spot, cfg)
    touch = Touchdown(ground_z=prof.collision_box[2] / 2)
    t0, t, phase, phase_t, lowest_y = fleet.time, 0.0, "brake", 0.0, math.inf
    while t < 6.0:
        s = fleet.state(0)
        fleet.external_position(0, s["pos"])                              # the mocap stream (item 1)
        if phase == "brake":
            rates, thrust = brake.command(s["pos"], s["vel"], s["quat"])
            rate_setpoint(fleet, 0, rates, thrust)
            if np.linalg.norm(s["vel"]) < cfg.brake_done_mps or t > cfg.brake_max_s:
                dist = float(np.linalg.norm(spot - s["pos"][:2]))
                duration = max(1.0, dist / cfg.approach_speed_mps)
                fleet.high_level(0, "go_to", x=spot[0], y=spot[1], z=cfg.approach_height_m, yaw=yaw,
                                 duration=duration)
                fleet.notify_setpoint_stop(0)
                phase, phase_t, brake_end = "approach", t + duration, t
        elif phase == "approach" and t >= phase_t:
            fleet.high_level(0, "land", height=cfg.land_height_m, yaw=None, duration=cfg.descent_s)
            phase = "land"
        assert fleet.status(0)["thrust"] > 0.0 or phase == "land"     # no gap in the hand-over
        fleet.advance(0.01)
        t = fleet.time - t0
        s = fleet.state(0)
        lowest_y = min(lowest_y, s["pos"][1])
        if touch.update(t, s["pos"], s["vel"]):
            break
    assert touch.t is not None and touch.t < 5.0, (touch.t, phase)
    assert abs(touch.vz) <= 0.5 and np.linalg.norm(touch.place[:2] - spot) < 0.15, touch.as_dict()
    assert brake_end < 0.8 and lowest_y > track.arena.y[0] - 0.1         # stopped before the fence (0.3 m)
    fleet.advance(cfg.descent_s)
    assert fleet.status(0)["thrust"] == fleet.idle_thrust(0) and not fleet.status(0)["crashed"]


def test_landing_pilot_flies_the_sequence():
    """The pilot's steps applied to the simulated firmware: two drones finishing side by side."""
    from cfrace.flight.landing.descent import LandingPilot
    track = load_track("lemniscate")
    fleet = SimFleet(track, "cf2x_paper", 2, arming_required=True, decks=())
    yaw = -math.pi / 2
    q = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
    for i in range(2):
        fleet.arm(i, True)
        for name in ("flightmode.stabModeRoll", "flightmode.stabModePitch"):
            fleet.set_param(i, name, 0)
        fleet.handle_setpoint(i, 0, 0, 0, 0)
        fleet.teleport(i, (-2.2 + 0.4 * i, 3.4, 0.75), (0.0, -4.5, 0.0), q)
    prof = fleet.profile
    stops = [stopping_point(fleet.state(i)["pos"], fleet.state(i)["vel"], 12.0) for i in range(2)]
    spots = choose_landing_spots(track, stops)
    setup = LandingSetup.for_race(track, prof)
    pilots = [LandingPilot(BrakeController(**setup.brake.__dict__), spots[i], setup.ground_z) for i in range(2)]
    done = [False, False]
    for _ in range(600):
        for i, pilot in enumerate(pilots):
            s = fleet.state(i)
            fleet.external_position(i, s["pos"])
            step = pilot.step(fleet.time, s["pos"], s["vel"], s["quat"])
            if step.rates_dps is not None:
                rate_setpoint(fleet, i, step.rates_dps, step.thrust_n)
            for name, args in step.high_level:
                assert fleet.high_level(i, name, **args) == 0
            if step.notify_stop:
                fleet.notify_setpoint_stop(i)
            if step.done and not done[i]:
                fleet.stop_setpoint(i)
                fleet.arm(i, False)
                done[i] = True
        if all(done):
            break
        fleet.advance(0.01)
    assert all(done)
    for i, pilot in enumerate(pilots):
        td = pilot.touchdown
        assert td.t is not None and td.t < 5.0 and abs(td.vz) <= 0.5, td.as_dict()
        assert np.linalg.norm(fleet.state(i)["pos"][:2] - spots[i]) < 0.15
        assert not fleet.status(i)["crashed"] and fleet.status(i)["thrust"] == fleet.idle_thrust(i)
    assert np.linalg.norm(spots[0] - spots[1]) >= LandingConfig().drone_separation_m


def test_landing_paths_of_drones_that_land_together_neither_cross_nor_touch(spot_work):
    """Drones landing at once fly straight to their spots at the same time: their paths keep
    path_separation_m (unless they start nearer) where the arena allows, also when the flight stack
    chooses one drone at a time handing over the paths flown already (otherwise the spot is clear of
    the drones that stay, else merely free); the choice is bounded in work (it runs in the tick): the
    straight-way check on at most max_tries candidates for each of the 5 searches of its rules."""
    from cfrace.flight.landing.spots import segment_gap as seg_dist

    def apart(stops, spots) -> list[bool]:
        return [seg_dist(stops[i], spots[i], stops[j], spots[j])
                >= min(cfg.path_separation_m, seg_dist(stops[i], stops[i], stops[j], spots[j])) - 1e-6
                for i in range(len(stops)) for j in range(i)]

    track, cfg = load_track("lemniscate"), LandingConfig()
    rng = np.random.default_rng(0)
    worst, batch, one_by_one = 0, [], []
    for _ in range(40):
        stops = np.column_stack([rng.uniform(-2.4, 2.4, 3), rng.uniform(2.1, 8.9, 3)])
        try:
            batch += apart(stops, choose_landing_spots(track, stops, cfg=cfg))
            paths, others, spots = [], [], []
            for stop in stops:   # one call per landing drone, as in the tick: its work
                spot_work.update(path_rule=0, paths_clear=0)
                spots.append(choose_landing_spots(track, [stop], others, cfg, paths)[0])
                worst = max(worst, spot_work["paths_clear"])
                paths.append((stop, spots[-1]))
                others.append(spots[-1])
            one_by_one += apart(stops, np.array(spots))
        except ValueError:   # no free spot at all: the flight stack lands that drone where it stops
            continue
    assert np.mean(batch) >= 0.95 and np.mean(one_by_one) >= 0.95, (np.mean(batch), np.mean(one_by_one))
    assert 0 < worst <= 5 * cfg.max_tries, worst


def test_eight_drones_landing_at_once_on_a_large_arena_get_the_whole_arena_s_spots_fast(monkeypatch, spot_work):
    """The complex track's arena holds 15 k candidate spots: the choice looks at the nearest ones
    first and gives the spots a search of the whole arena gives; the eight choices together took about
    20 ms of CPU here (the flight tick makes one a tick: tests/test_flight_landing_queue.py). Asserted
    by the work that bounds it, the same on every CPU: each choice puts at most NEAR_CANDIDATES
    candidates through the path rule and at most max_tries through the straight-way check."""
    import cfrace.flight.landing.spots as ld

    track, cfg = load_track("complex"), LandingConfig()
    rng = np.random.default_rng(3)
    a = track.arena
    ld.candidate_spots(track, cfg)                       # as LandingSetup.for_race does before the race
    for _ in range(4):
        stops = np.column_stack([rng.uniform(a.x[0] + 0.1, a.x[1] - 0.1, 8), rng.uniform(a.y[0] + 0.1, a.y[1] - 0.1, 8)])
        paths, others, spots = [], [], []
        for stop in stops:                               # one tick: every drone starts landing (race end)
            spot_work.update(path_rule=0, paths_clear=0)
            spots.append(ld.choose_landing_spots(track, [stop], others, cfg, paths)[0])
            assert spot_work["path_rule"] <= ld.NEAR_CANDIDATES and spot_work["paths_clear"] <= cfg.max_tries
            paths.append((stop, spots[-1]))
            others.append(spots[-1])
        with monkeypatch.context() as m:                 # the whole arena every time: the same spots
            m.setattr(ld, "NEAR_CANDIDATES", 10 ** 9)
            paths, others, full = [], [], []
            for stop in stops:
                full.append(ld.choose_landing_spots(track, [stop], others, cfg, paths)[0])
                paths.append((stop, full[-1]))
                others.append(full[-1])
        assert np.array_equal(np.array(spots), np.array(full))


#: the loser's estimate when the race ended in a real-time flight against `sim serve` (the walkthrough's
#: `fly`, ds against ours on cf2x_paper): 0.6 m before its target, the finish gate 5 (-2.0, 3.5, 0.75),
#: at 4.4 m/s towards the gate's left bar
RACE_END_STATE = dict(pos=(-1.949, 4.091, 0.84), vel=(-3.34, -2.62, -1.14), quat=(0.8041, -0.1291, 0.3099, -0.4905))


def test_braking_at_the_race_end_into_the_gate_ahead_crashes_so_the_drone_flies_through_first():
    """From that state the landing's braking (on the simulated firmware) hits gate 5's frame within
    0.3 s: the simulator drops the crashed drone to the floor in one step, which the flight loop saw as
    three pose outliers and then a 16 m/s speed stop. brakes_into_gate finds it: at the race's end such
    a drone flies on through the gate on its policy before it lands (SoftState.land_after_race)."""
    from cfrace.flight.landing.descent import LandingPilot
    from cfrace.flight.safety.failsafe import brakes_into_gate
    track = load_track("lemniscate")
    fleet = SimFleet(track, "cf2x_paper", 1, arming_required=True, decks=())
    fleet.arm(0, True)
    for name in ("flightmode.stabModeRoll", "flightmode.stabModePitch"):
        fleet.set_param(0, name, 0)
    fleet.handle_setpoint(0, 0, 0, 0, 0)
    fleet.teleport(0, RACE_END_STATE["pos"], RACE_END_STATE["vel"], RACE_END_STATE["quat"])
    setup = LandingSetup.for_race(track, fleet.profile)
    pilot = LandingPilot(BrakeController(**{**setup.brake.__dict__, "hold_z": None}), np.array([-2.0, 4.2]),
                         setup.ground_z)
    for _ in range(50):
        s = fleet.state(0)
        fleet.external_position(0, s["pos"])
        step = pilot.step(fleet.time, s["pos"], s["vel"], s["quat"])
        assert step.rates_dps is not None                     # still braking
        rate_setpoint(fleet, 0, step.rates_dps, step.thrust_n)
        fleet.advance(0.01)
        if fleet.status(0)["crashed"]:
            break
    assert fleet.status(0)["crash_reason"] == "gate_frame" and fleet.time < 0.3
    gate = setup.gates[5]
    assert brakes_into_gate(RACE_END_STATE["pos"], RACE_END_STATE["vel"], gate, setup)
    # a drone turning into gate 3 from the side (a lockstep race ended by the timeout at 6.79 s): its
    # straight path passes 1.6 m beside the gate, but braking it drifted on into the frame's side bar
    assert brakes_into_gate((0.751, 7.882, 0.689), (4.54, -1.69, -0.61), setup.gates[3], setup)
    # not: moving away from the gate, far from it, or passing its plane far beside the frame
    assert not brakes_into_gate((-2.0, 3.0, 0.75), (0.0, -4.0, 0.0), gate, setup)
    assert not brakes_into_gate((-2.0, 7.0, 0.75), (0.0, -4.0, 0.0), gate, setup)
    assert not brakes_into_gate((2.0, 4.5, 0.75), (0.0, -4.0, 0.0), gate, setup)


def test_a_path_along_a_gate_frame_is_not_clear():
    """A drone that braked to a stop 0.1 m in front of gate 5's plane (a lockstep race ended by the
    timeout at 3.34 s): its go-to along the frame touched the frame's side bar. Near a gate, a clear
    path leads away from it."""
    from cfrace.flight.landing.spots import path_clear
    track = load_track("lemniscate")
    here = np.array([-2.01, 3.61])
    assert not path_clear(track, here, np.array([-0.7, 3.7]), LandingConfig().path_clearance_m)
    assert path_clear(track, here, np.array([-2.0, 4.3]), LandingConfig().path_clearance_m)
    assert path_clear(track, np.array([0.5, 4.5]), np.array([0.5, 3.0]), LandingConfig().path_clearance_m)
    assert not path_clear(track, np.array([1.0, 4.3]), np.array([0.5, 3.0]), LandingConfig().path_clearance_m)


def test_after_the_race_a_drone_flies_through_the_gate_ahead_then_lands():
    """SoftState.land_after_race: the drone of RACE_END_STATE keeps racing until braking would take it
    into no gate ahead (it is through) and not out of the fence, or 1 s has passed; a drone that can
    stop clear of its gate and the fence lands at once; one through a gate but too close to the next
    flies on, and so does one heading for the wall."""
    from types import SimpleNamespace

    from cfrace.flight.safety.failsafe import FLY_THROUGH_MAX_S, SoftState
    from cfrace.drone import load_profile
    setup = LandingSetup.for_race(load_track("lemniscate"), load_profile("cf2x_paper"))
    fence = Fence.from_track(setup.track, SafetyConfig().geofence_margin_m)

    def drone(name):
        return SimpleNamespace(stopped=False, landing=None, frozen_pos=None, name=name, body=name, landing_result=None)

    def est(pos, vel):
        return SimpleNamespace(pos=np.array(pos), vel=np.array(vel), valid=True)

    through, late, away = drone("a"), drone("b"), drone("c")
    drones = [through, late, away]
    ests = [est(RACE_END_STATE["pos"], RACE_END_STATE["vel"])] * 2 + [est((0.0, 6.5, 1.0), (0.0, 4.0, 0.0))]
    soft = SoftState(3)
    soft.land_after_race(drones, ests, 3.71, 3.71, [5, 5, 0], fence, setup)
    assert through.landing is None and late.landing is None and away.landing is not None
    ests[0] = est((-2.3, 3.2, 0.8), (1.0, -2.0, 0.0))                      # a is through gate 5, turning
    soft.land_after_race(drones, ests, 3.95, 3.71, [0, 5, 0], fence, setup)
    assert through.landing is not None and through.landing_result["reason"] == "race_end" and late.landing is None
    soft.land_after_race(drones, ests, 3.71 + FLY_THROUGH_MAX_S, 3.71, [0, 5, 0], fence, setup)
    assert late.landing is not None                                       # not through in time: lands anyway
    # ours on cf21bl, a race ended at 1.0 s: through gate 1 at 1.14 s at 6 m/s, 2.5 m before gate 2 it
    # braked into gate 2's top bar (the rule looked only at the gate ahead at the end); it flies on
    nxt = drone("d")
    soft.land_after_race([nxt], [est((-0.12, 5.51, 1.39), (-4.5, 4.3, 0.2))], 1.14, 1.0, [2], fence, setup)
    assert nxt.landing is None
    # heading for the wall, no gate ahead of it: braking would take it out of the fence (brakes_unsafe,
    # the rule of a deferred mid-race landing too); it flies on until it has turned, then lands
    wall = drone("e")
    soft.land_after_race([wall], [est((1.2, 5.0, 1.0), (5.0, 0.0, 0.0))], 1.0, 1.0, [1], fence, setup)
    assert wall.landing is None
    soft.land_after_race([wall], [est((1.6, 5.2, 1.0), (1.0, 4.9, 0.0))], 1.1, 1.0, [1], fence, setup)
    assert wall.landing is not None and wall.landing_result["reason"] == "race_end"


def test_drones_that_brake_side_by_side_swap_spots_rather_than_fly_across_each_other():
    """ds against ours on cf21bl, a lockstep race ended by the timeout at 1.18 s: both flew through
    gate 2 side by side and braked to a stop 0.16 m apart, then flew go-tos to the spots chosen at
    the landing's start across each other, touched for 0.3 s and crashed. The drone that hands over
    first swaps spots with the one still braking when that makes their paths shorter together."""
    from types import SimpleNamespace

    from cfrace.drone import load_profile
    from cfrace.flight.landing.descent import LandingPilot
    from cfrace.flight.landing.spots import swap_pays
    from cfrace.flight.safety.failsafe import SoftState
    setup = LandingSetup.for_race(load_track("lemniscate"), load_profile("cf21bl"))
    here, there = np.array([-2.15, 7.98, 0.6]), np.array([-2.25, 7.85, 0.57])
    south, north = np.array([-2.0, 7.7]), np.array([-2.0, 8.5])
    assert swap_pays(here[:2], south, there[:2], north) and not swap_pays(here[:2], north, there[:2], south)

    def drones(other_phase):
        out = []
        for name, spot, pos in (("ego", north, there), ("opp", south, here)):
            pilot = LandingPilot(setup.brake, spot.copy(), setup.ground_z, setup.cfg, pos=pos)
            pilot.phase = other_phase if name == "ego" else pilot.phase
            out.append(SimpleNamespace(name=name, body=name, stopped=False, frozen_pos=None, landing=pilot,
                                       landing_result={"spot": list(spot)}))
        return out

    braking = drones("brake")
    soft = SoftState(2)
    assert np.allclose(soft._respot(braking, 1, setup, here, south), north)     # opp hands over first
    assert np.allclose(braking[0].landing.spot, south) and braking[0].landing_result["spot"] == [-2.0, 7.7]
    assert sum("spots swapped" in r[1]["text"] for r in soft.pending_records) == 2
    flying = drones("approach")                  # the other one's go-to is under way: nothing to swap
    assert np.allclose(SoftState(2)._respot(flying, 1, setup, here, south), south)
    assert np.allclose(flying[0].landing.spot, north)


def test_a_braked_drone_holds_while_a_lower_one_lands_along_its_path():
    """ours against ds on cf21bl, a lockstep race ended by the timeout at 4.42 s: both braked to a
    stop 0.1 m apart seen from above, ego 0.38 m over opp, and flew their go-tos west along the same
    line; ego, faster and descending, came down on opp (0.15 m) and both crashed. A braked drone now
    holds where it is while its path runs within path_separation_m of the way ahead of a drone that
    goes first (one flying its go-to, or one braking at a lower height), and goes once that way is
    clear; the lower drone does not wait for the higher one, and a hold ends after hold_max_s."""
    from types import SimpleNamespace

    from cfrace.drone import load_profile
    from cfrace.flight.landing.descent import APPROACH, HOLD, LandingPilot
    from cfrace.flight.safety.failsafe import SoftState
    setup = LandingSetup.for_race(load_track("lemniscate"), load_profile("cf21bl"))
    high, low = np.array([0.70, 2.97, 0.69]), np.array([0.75, 2.87, 0.31])
    west, far_west = np.array([0.0, 2.8]), np.array([-0.8, 2.7])
    drones, soft = [], SoftState(2)
    for name, spot, pos in (("ego", west, high), ("opp", far_west, low)):
        pilot = LandingPilot(BrakeController(**{**setup.brake.__dict__, "hold_z": None}), spot.copy(), setup.ground_z,
                             setup.cfg)
        drones.append(SimpleNamespace(name=name, body=name, stopped=False, frozen_pos=None, landing=pilot,
                                      landing_result={"spot": list(spot)}))
    hover = np.array([1.0, 0.0, 0.0, 0.0])
    for i, d in enumerate(drones):                  # both still braking (their hold heights are set)
        d.landing.brake.hold_z = float((high, low)[i][2])
        d.landing.may_go = lambda t, i=i: soft._may_go(drones, i, setup, t)
        d.landing.step(0.0, (high, low)[i], [1.0, 0.0, 0.0], hover)
    step = drones[0].landing.step(0.5, high, [0.0, 0.0, 0.0], hover)     # ego braked: opp is in its way
    assert drones[0].landing.phase == HOLD and step.rates_dps is not None and not step.high_level
    assert sum("until opp is out of its way" in r[1]["text"] for r in soft.pending_records) == 1
    step = drones[1].landing.step(0.5, low, [0.0, 0.0, 0.0], hover)      # opp braked: it goes first
    assert drones[1].landing.phase == APPROACH and step.high_level[0][0] == "go_to"
    drones[0].landing.step(1.0, high, [0.0, 0.0, 0.0], hover)
    assert drones[0].landing.phase == HOLD                                # opp still on ego's line
    drones[1].landing.pos = np.array([-0.45, 2.74, 0.25])                 # opp 0.45 m past ego's spot
    step = drones[0].landing.step(1.5, high, [0.0, 0.0, 0.0], hover)
    assert drones[0].landing.phase == APPROACH and step.high_level[0][0] == "go_to" and step.notify_stop
    stuck = LandingPilot(BrakeController(**setup.brake.__dict__), west.copy(), setup.ground_z, setup.cfg,
                         may_go=lambda t: False)                          # never clear: goes after hold_max_s
    stuck.step(0.0, high, [0.0, 0.0, 0.0], hover)
    assert stuck.phase == HOLD
    stuck.step(setup.cfg.hold_max_s + 0.01, high, [0.0, 0.0, 0.0], hover)
    assert stuck.phase == APPROACH


def test_paths_checked_together_are_judged_as_each_alone():
    """spots.paths_clear samples paths of different lengths in one padded batch: each path's verdict is
    the one it gets alone, near gates and obstacles and far from them (both tracks, with obstacles)."""
    from cfrace.flight.landing.spots import paths_clear
    rng, seen = np.random.default_rng(3), set()
    for name in ("lemniscate", "complex"):
        track = load_track(name)
        assert track.obstacles
        a, clear = track.arena, LandingConfig().path_clearance_m
        for _ in range(30):
            start = np.array([rng.uniform(*a.x), rng.uniform(*a.y)])
            ends = np.concatenate([np.column_stack([rng.uniform(*a.x, 12), rng.uniform(*a.y, 12)]),
                                   start + rng.normal(0.0, 0.3, (6, 2)), start[None]])
            batch = paths_clear(track, start, ends, clear)
            alone = [bool(paths_clear(track, start, e[None], clear)[0]) for e in ends]
            assert batch.tolist() == alone
            seen |= set(alone)
    assert seen == {True, False}


def test_a_drone_that_falls_on_the_floor_while_braking_is_stopped_there_and_not_called_landed():
    """A drone diving low when its landing begins can hit the floor before the firmware's go-to: it
    is stopped at once (no go-to to a drone on the floor), and its landing result says it crashed
    (floor_braking, not down); one resting on the floor when its landing began is simply down."""
    from types import SimpleNamespace

    from cfrace.drone import load_profile
    from cfrace.flight.landing.descent import BrakeController, LandingPilot
    from cfrace.flight.safety.failsafe import land_step

    quat = np.array([1.0, 0.0, 0.0, 0.0])

    def land(path):
        pilot = LandingPilot(BrakeController(0.04, 0.9), np.array([0.0, 3.0]), 0.015)
        d = SimpleNamespace(landing=pilot, landing_result={"t_start": 0.0}, stopped=False,
                            thrust_curve=load_profile("cf2x_paper").thrust_curve)
        commands, out = [], "braking"
        for k, (pos, vel) in enumerate(path):
            est = SimpleNamespace(pos=np.array(pos, float), vel=np.array(vel, float), quat=quat, valid=True)
            if land_step(0, [d], [est], 0.1 * k, commands, 8.0) is None and "down" in d.landing_result:
                out = d.landing_result
                break
        return pilot, out, commands

    pilot, result, commands = land([([0.0, 2.0, 0.30], [2.0, 0.0, -1.5]), ([0.2, 2.0, 0.03], [2.0, 0.0, -1.5])])
    assert pilot.hit_floor and not commands                   # stopped where it fell: no go-to, no land
    assert result["down"] is False and result["cut"] == "floor_braking" and result["vz_mps"] == pytest.approx(-1.5)
    pilot, result, commands = land([([0.0, 2.0, 0.016], [0.0, 0.0, 0.0])])    # resting on the floor
    assert not pilot.hit_floor and result["down"] is True and "cut" not in result and not commands
