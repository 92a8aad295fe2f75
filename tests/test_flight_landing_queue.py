"""Landing spots are chosen a few drones per tick (SoftState.choose_spots): when a whole swarm starts
landing in one tick the choice spreads over ticks, each drone brakes on until its spot is known, and
the spots are the ones a choice of all of them in one tick gives."""

from types import SimpleNamespace

import numpy as np

from cfrace.drone import load_profile
from cfrace.flight.landing.descent import BRAKE, HOLD, LandingPilot, LandingSetup, stopping_point
from cfrace.flight.safety.failsafe import SPOTS_PER_TICK, SoftState
from cfrace.flight.landing.spots import NEAR_CANDIDATES, LandingConfig, choose_landing_spots
from cfrace.track import load_track


def drone(name):
    return SimpleNamespace(stopped=False, landing=None, frozen_pos=None, name=name, body=name, landing_result=None)


def test_eight_drones_that_start_landing_together_get_their_spots_one_tick_after_another(spot_work):
    """SPOTS_PER_TICK choices a tick, each bounded by its work (the path rule on the NEAR_CANDIDATES
    nearest, the straight-way check on max_tries per rule tried), not by this machine's CPU time."""
    setup = LandingSetup.for_race(load_track("complex"), load_profile("cf2x_paper"))
    a, rng = setup.track.arena, np.random.default_rng(5)
    for _ in range(3):
        pos = np.column_stack([rng.uniform(a.x[0] + 1, a.x[1] - 1, 8), rng.uniform(a.y[0] + 1, a.y[1] - 1, 8),
                               np.full(8, 1.0)])
        vel = rng.normal(0.0, 3.0, (8, 3)) * [1, 1, 0]
        drones, soft = [drone(f"d{k + 1}") for k in range(8)], SoftState(8)
        for i in range(8):               # the race's end: every drone starts landing in one tick
            soft.start_landing(drones, i, SimpleNamespace(pos=pos[i], vel=vel[i]), 5.0, "race_end", setup)
        assert all(d.landing.spot is None and d.landing.phase == BRAKE for d in drones)
        chosen = []
        while soft.spot_queue:
            spot_work.update(path_rule=0, paths_clear=0)
            soft.choose_spots(drones, setup)
            assert spot_work["path_rule"] <= SPOTS_PER_TICK * NEAR_CANDIDATES, spot_work
            assert spot_work["paths_clear"] <= SPOTS_PER_TICK * 5 * LandingConfig().max_tries, spot_work
            now = [i for i, d in enumerate(drones) if d.landing.spot is not None]
            assert len(now) - len(chosen) == SPOTS_PER_TICK and now[:len(chosen)] == chosen
            chosen = now
        assert chosen == list(range(8))
        # the same spots as all eight chosen in one tick, first come first (each spot and path blocks the next)
        paths, others = [], []
        for i in range(8):
            stop = stopping_point(pos[i], vel[i], setup.brake.accel_max)[:2]
            spot = choose_landing_spots(setup.track, [stop], others, setup.cfg, paths)[0]
            assert np.array_equal(drones[i].landing.spot, spot) and drones[i].landing_result["spot"] == \
                [round(float(v), 3) for v in spot]
            paths.append((stop, spot))
            others.append(spot)
        texts = [r[1]["text"] for r in soft.pending_records]
        assert len(texts) == 8 and all(t.startswith("race_end: landing at") for t in texts)


def test_a_drone_without_its_spot_brakes_on_and_those_behind_it_wait():
    setup = LandingSetup.for_race(load_track("lemniscate"), load_profile("cf2x_paper"))
    pilot = LandingPilot(setup.brake, None, setup.ground_z, setup.cfg)
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    for k in range(5):                   # at rest: braking is over, but no spot to fly to yet
        step = pilot.step(0.01 * k, np.array([0.0, 5.0, 1.0]), np.zeros(3), quat)
        assert pilot.phase == BRAKE and step.rates_dps is not None and not step.high_level
    pilot.spot = np.array([1.0, 5.0])
    step = pilot.step(0.05, np.array([0.0, 5.0, 1.0]), np.zeros(3), quat)
    assert step.high_level[0][0] == "go_to" and step.notify_stop
    # a braked drone does not start its go-to while a drone that goes first has no spot yet
    drones = [drone("low"), drone("high")]
    soft = SoftState(2)
    for i, z in enumerate((0.6, 1.2)):
        soft.start_landing(drones, i, SimpleNamespace(pos=np.array([0.0, 4.0 + i, z]), vel=np.zeros(3)), 1.0,
                           "race_end", setup)
        drones[i].landing.pos, drones[i].landing.brake.hold_z = np.array([0.0, 4.0 + i, z]), z
    drones[1].landing.spot, drones[1].landing.phase = np.array([1.0, 5.0]), HOLD
    assert not soft._may_go(drones, 1, setup, 1.1)            # "low" goes first, and its way is not known
    soft.choose_spots(drones, setup, budget=1)                 # "low" gets its spot (first come first)
    assert drones[0].landing.spot is not None


def test_a_drone_hemmed_in_by_other_paths_gets_its_spot_without_walking_the_arena(spot_work):
    """An 8-drone lockstep race on the complex track ended by the time-out at 1.5 s: a drone stopping
    0.1-0.15 m from two other landing drones' paths. No spot within reach keeps clear of those paths,
    and the search for one walked all 15 k candidates of the arena: about 100 ms of CPU in one tick (the
    loop stops every drone at 100 ms; the old code fails the bound below). The path rule now looks at the nearest candidates only; the spot is
    the one the whole arena gave (the nearest clear of the drones that stay). Asserted by the work done
    (the old code put 14 k candidates through the path rule), not by this machine's CPU time (8 ms)."""
    track, cfg = load_track("complex"), LandingConfig()
    stops = [[-2.803, 1.636]]
    others = [[2.843, 1.874], [3.126, 2.156], [-2.9, 1.4], [-2.1, 1.3]]
    paths = [([-2.934, 1.504], [-2.9, 1.4]), ([-2.693, 1.73], [-2.1, 1.3])]
    spot = choose_landing_spots(track, stops, others, cfg, paths)[0]
    assert 0 < spot_work["path_rule"] <= NEAR_CANDIDATES and spot_work["paths_clear"] <= cfg.max_tries
    assert np.allclose(spot, [-3.5, 2.0])
