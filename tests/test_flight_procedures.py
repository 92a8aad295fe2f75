"""Hover start and the hover test on the simulated firmware (lockstep: DirectSimLink, fleet.advance)."""

import numpy as np
import pytest

from cfrace.errors import FlightError
from cfrace.flight.link.protocol import DirectSimLink
from cfrace.flight.landing.procedures import HoverConfig, hover_start, hover_start_positions, hover_test
from cfrace.simcf.firmware import SimFleet
from cfrace.track import load_track


def fleet_links(profile="cf21bl", drones=2):
    fleet = SimFleet("lemniscate", profile, drones, arming_required=True, decks=())
    links = [DirectSimLink(fleet, i, clock=lambda: fleet.time) for i in range(drones)]
    for link in links:
        link.connect()
        link.setup()
    return fleet, links, lambda: fleet.poses()[1]


@pytest.mark.parametrize("profile", ["cf2x_paper", "cf21bl"])
def test_hover_start_takes_off_to_the_start_positions_and_holds(profile):
    fleet, links, poses = fleet_links(profile)
    track = load_track("lemniscate")
    targets, yaw = hover_start_positions(track, 2)
    assert targets[:, 2] == pytest.approx(track.gates[0][2])
    report = hover_start(links, ["cf1", "cf2"], poses, fleet.advance, targets, yaw)
    assert max(report["hold_error_m"]) <= 0.1 and report["t_s"] < 8.0
    for i in range(2):
        assert np.linalg.norm(fleet.state(i)["pos"] - targets[i]) < 0.1
        assert fleet.status(i)["setpoint_source"] == "high-level"
    # the race's first rate setpoint takes over at once (the low-level priority)
    links[0].send(0.0, 0.0, 0.0, 30000)
    assert fleet.status(0)["setpoint_source"] == "legacy" and fleet.status(0)["high_level"] == "idle"


def test_hover_start_that_cannot_settle_lands_and_fails():
    fleet, links, poses = fleet_links()
    targets, yaw = hover_start_positions(load_track("lemniscate"), 2)
    with pytest.raises(FlightError, match="did not settle"):
        hover_start(links, ["cf1", "cf2"], poses, fleet.advance, targets, yaw,
                    HoverConfig(tolerance_m=0.0001, timeout_s=0.5))
    for i in range(2):
        assert fleet.state(i)["pos"][2] < 0.05 and fleet.status(i)["thrust"] == 0.0


def test_hover_test_holds_and_lands_softly():
    fleet, links, poses = fleet_links(drones=1)
    x0 = fleet.state(0)["pos"].copy()
    report = hover_test(links[0], "cf1", poses, fleet.advance, height=0.5, hold_s=2.0,
                        ground_z=fleet.profile.collision_box[2] / 2)
    assert report["hold_error_m"] < 0.1
    td = report["touchdown"]
    assert td["t"] is not None and abs(td["vz_mps"]) <= 0.5
    assert np.linalg.norm(np.array(td["place"][:2]) - x0[:2]) < 0.1
    assert fleet.status(0)["thrust"] == 0.0 and not fleet.status(0)["crashed"] and not fleet.status(0)["armed"]


def test_first_flight_checks_then_hovers_each_drone():
    """`cfrace fly --check --hover` on simulated drones (lockstep I/O of the dry-run)."""
    from cfrace.flight.config import FlightConfig
    from cfrace.rehearsal.dryrun import sim_io
    from cfrace.flight.landing.procedures import first_flight
    from cfrace.flight.setup import resolve_race

    cfg = FlightConfig(track="lemniscate", ego="ours", opp="ds", profile="cf21bl", quiet=True)
    setup = resolve_race(cfg)
    fleet = SimFleet(setup.track, setup.profile, 2, decks=())
    report = first_flight(setup, sim_io(cfg, fleet, lockstep=True, uris=["sim://0", "sim://1"]), check=True,
                          hover_drones=[1])
    assert report["ok"], report["lines"]
    assert len(report["checks"]) == 10 and [h["drone"] for h in report["hover"]] == [1]
    assert report["hover"][0]["hold_error_m"] < 0.1 and "hover" in report["lines"][-1]
    assert all(fleet.status(i)["thrust"] == 0.0 and not fleet.status(i)["armed"] for i in range(2))
    fleet.set_battery(0, 0.0)
    report = first_flight(setup, sim_io(cfg, fleet, lockstep=True, uris=["sim://0", "sim://1"]), check=True,
                          hover_drones=[0, 1])
    assert not report["ok"] and report["hover"] == []            # a failed check: no hover, nothing armed
