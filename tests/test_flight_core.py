"""Flight core pieces: link conventions (direct and real cflib over UDP), clocks, race progress,
the observation agreement with the simulator/env, and the loop's race logic."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
import torch

from cfrace.errors import LinkError
from cfrace.flight.clock import LockstepClock, RealClock
from cfrace.flight.link import (DirectSimLink, RecordingLink, cflib_setpoint_args, open_link, packet_values,
                                thrust_to_counts)
from cfrace.flight.progress import FastRaceProgress
from cfrace.sim.gates import RaceProgress
from cfrace.track import load_track

PROFILE = "cf2x_paper"


@pytest.fixture(scope="module")
def track():
    return load_track("lemniscate")


def airborne_fleet(track):
    from cfrace.simcf.firmware import SimFleet

    start = np.array([[0.0, 5.0, 1.5], [1.0, 4.0, 1.5]])
    return SimFleet(track, PROFILE, 2, start_positions=start, obstacles=False)


def hover_counts(fleet) -> int:
    return thrust_to_counts(fleet.profile.mass * 9.81, fleet.profile.thrust_curve)


# ---------------------------------------------------------------------------------------------- links

def test_packet_conventions():
    # cflib negates pitch; the firmware negates the legacy yaw rate
    assert packet_values(10.0, 20.0, 30.0) == (10.0, -20.0, -30.0)
    assert cflib_setpoint_args(10.0, 20.0, 30.0) == (10.0, 20.0, -30.0)
    roll, pitch, yaw = cflib_setpoint_args(10.0, 20.0, 30.0)
    assert (roll, -pitch, yaw) == packet_values(10.0, 20.0, 30.0)   # what cflib puts on the wire


def test_thrust_counts_follow_the_calibration_curve():
    from cfrace.drone import load_profile

    curve = load_profile(PROFILE).thrust_curve
    assert thrust_to_counts(0.0, curve) == 0
    assert thrust_to_counts(1e3, curve) == 65535
    mid = thrust_to_counts(0.2, curve)
    assert isinstance(mid, int) and abs(float(curve.to_newtons(mid)) - 0.2) < 1e-4


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_direct_link_gives_the_drone_the_body_rates_asked_for(track, axis):
    fleet = airborne_fleet(track)
    link = DirectSimLink(fleet, 0, clock=lambda: fleet.time)
    link.connect()
    link.setup()
    assert fleet.get_param(0, "flightmode.stabModeRoll") == 0 and fleet.get_param(0, "flightmode.stabModePitch") == 0
    rates = [0.0, 0.0, 0.0]
    rates[axis] = 60.0
    for _ in range(10):
        link.send(*rates, hover_counts(fleet))
        fleet.advance(0.01)
    omega = np.degrees(fleet.state(0)["omega"])
    assert omega[axis] == pytest.approx(60.0, abs=8.0), omega
    assert np.all(np.abs(np.delete(omega, axis)) < 5.0), omega
    link.stop()
    fleet.advance(0.02)
    assert fleet.status(0)["thrust"] == 0.0 and not fleet.status(0)["armed"]
    assert fleet.status(1)["setpoints_received"] == 0       # the other drone got nothing


@pytest.fixture()
def udp_fleet(track):
    from cfrace.simcf.server import SimCrazyflieServer

    fleet = airborne_fleet(track)
    server = SimCrazyflieServer(fleet, base_port=0, realtime=False).start()
    yield fleet, server
    server.stop()


def _wait(cond, timeout=3.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.005)
    return False


def test_cflib_link_over_udp_flies_the_rates_asked_for(udp_fleet):
    fleet, server = udp_fleet
    link = open_link(server.uris[0])
    assert type(link).__name__ == "CflibLink"
    link.connect(10.0)
    assert link.quality.connected
    fleet.set_param(0, "flightmode.stabModeRoll", 1)      # as after a reboot: setup must fix it
    link.setup()
    assert fleet.get_param(0, "flightmode.stabModeRoll") == 0
    assert fleet.get_param(0, "flightmode.stabModePitch") == 0
    assert _wait(lambda: fleet.status(0)["armed"])
    base = fleet.status(0)["setpoints_received"]
    link.send(0.0, 50.0, -40.0, hover_counts(fleet))
    assert _wait(lambda: fleet.status(0)["setpoints_received"] > base)
    for _ in range(10):
        fleet.advance(0.01)
    omega = np.degrees(fleet.state(0)["omega"])
    assert omega[1] == pytest.approx(50.0, abs=8.0) and omega[2] == pytest.approx(-40.0, abs=8.0), omega
    assert abs(omega[0]) < 5.0
    assert _wait(lambda: link.quality.rx_age(time.monotonic()) < 0.2)   # echo pings answered
    link.stop()
    assert _wait(lambda: not fleet.status(0)["armed"])
    fleet.advance(0.02)
    assert fleet.status(0)["thrust"] == 0.0
    link.close()
    assert not link.quality.connected
    assert fleet.status(1)["setpoints_received"] == 0


def _free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_cflib_link_errors_are_one_line():
    uri = f"udp://127.0.0.1:{_free_udp_port()}"
    with pytest.raises(LinkError) as e:
        open_link(uri).connect(2.0)
    msg = str(e.value)
    assert msg.startswith(uri) and "\n" not in msg and ("nothing listens" in msg or "no answer" in msg)
    with pytest.raises(LinkError, match=r"^radio://0/80/2M/E7E7E7E7E7: no Crazyradio found"):
        open_link("radio://0/80/2M/E7E7E7E7E7").connect(2.0)
    with pytest.raises(LinkError, match="unknown link URI"):
        open_link("tcp://1.2.3.4")
    with pytest.raises(LinkError, match="needs the in-process simulator"):
        open_link("sim://0")


def test_cflib_link_times_out_on_silence():
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:   # bound but never answers
        s.bind(("127.0.0.1", 0))
        uri = f"udp://127.0.0.1:{s.getsockname()[1]}"
        t0 = time.monotonic()
        with pytest.raises(LinkError, match=r"no answer within 0.5 s$"):
            open_link(uri).connect(0.5)
        assert time.monotonic() - t0 < 3.0


def test_cflib_detects_link_loss_by_silence(udp_fleet):
    fleet, server = udp_fleet
    link = open_link(server.uris[1])
    link.connect(10.0)
    assert _wait(lambda: link.quality.rx_age(time.monotonic()) < 0.2)
    server.stop()                                          # the drone goes away
    assert _wait(lambda: link.quality.rx_age(time.monotonic()) > 0.5 or not link.quality.connected, 3.0)
    link.close()


# ---------------------------------------------------------------------------------------------- clocks

class FakeTime:
    def __init__(self):
        self.now = 100.0
        self.sleeps = []

    def perf(self):
        return self.now

    def sleep(self, s):
        self.sleeps.append(s)
        self.now += s + 0.0001           # every sleep overshoots by 0.1 ms


def test_real_clock_uses_absolute_deadlines_without_drift():
    ft = FakeTime()
    clock = RealClock(0.01, perf=ft.perf, sleep=ft.sleep)
    clock.start()
    ticks = []
    for _ in range(1000):
        tick = clock.wait_next()
        ticks.append(tick)
        ft.now += 0.002                  # work
    assert ticks[-1].k == 999
    assert ticks[-1].t == pytest.approx(9.99 + 0.0001, abs=1e-9)   # overshoot does not accumulate
    assert max(t.late_s for t in ticks) < 0.00011 and clock.skipped == 0


def test_real_clock_skips_missed_ticks_instead_of_bursting():
    ft = FakeTime()
    clock = RealClock(0.01, perf=ft.perf, sleep=ft.sleep)
    clock.start()
    a = clock.wait_next()
    ft.now += 0.035                      # a 35 ms stall inside tick 0
    b = clock.wait_next()
    assert b.late_s == pytest.approx(0.025) and b.skipped == 2 and b.k == 3   # ticks 1, 2 dropped
    c = clock.wait_next()                # back on the grid, not early
    assert c.k == 4 and c.t == pytest.approx(0.04 + 0.0001) and c.skipped == 0
    assert [a.k, b.k, c.k] == [0, 3, 4] and clock.skipped == 2


def test_lockstep_clock_advances_the_world_one_tick_per_iteration():
    steps = []
    clock = LockstepClock(0.01, advance=steps.append)
    clock.start()
    ks = [clock.wait_next().k for _ in range(3)]
    clock.stall(0.05)
    t = clock.wait_next()
    assert ks == [0, 1, 2] and steps[:2] == [0.01, 0.01]
    assert t.k == 8 and t.late_s == pytest.approx(0.05) and t.skipped == 5 and steps[-1] == pytest.approx(0.06)
    assert clock.now() == pytest.approx(0.08)


# ---------------------------------------------------------------------------------------------- progress

def gate_path(track, speed: float, dt: float = 0.01, laps: int = 1, lateral: float = 0.0):
    """World positions sampled at dt along straight lines through every gate (+n -> -n)."""
    g = track.gate_array()
    pts = []
    for _ in range(laps):
        for x, y, z, yaw in g:
            n = np.array([math.cos(yaw), math.sin(yaw), 0.0])
            side = np.array([-n[1], n[0], 0.0]) * lateral
            c = np.array([x, y, z]) + side
            pts += [c + 0.6 * n, c - 0.6 * n]
    out = [pts[0] + np.array([0, 0, 0.0])]
    for a, b in zip(pts[:-1], pts[1:]):
        steps = max(1, int(np.linalg.norm(b - a) / (speed * dt)))
        out += [a + (b - a) * (k / steps) for k in range(1, steps + 1)]
    return np.array(out)


def test_fast_progress_matches_the_simulator_rule(track):
    rng = np.random.default_rng(0)
    paths = [gate_path(track, 3.0, laps=2), gate_path(track, 5.0, laps=2, lateral=0.45),
             gate_path(track, 4.0, lateral=0.55)]
    for trial in range(6):   # random walks around the gates: passes, misses and frame hits
        start = track.gate_array()[trial % 6, :3] + rng.normal(0, 0.3, 3)
        paths.append(start + np.cumsum(rng.normal(0, 0.08, (600, 3)), axis=0))
    n = min(len(p) for p in paths[:2])
    pairs = [np.stack([paths[0][:n], paths[1][:n]], 1)] + [np.stack([p, p[::-1]], 1) for p in paths[2:]]
    hits = passes = 0
    for pos in pairs:
        a, b = RaceProgress(track.gate_array(), 2), FastRaceProgress(track.gate_array(), 2)
        for k, p in enumerate(pos):
            ra, rb = a.update(k * 0.01, p), b.update(k * 0.01, p)
            for x, y in zip(ra, rb):
                assert np.array_equal(np.asarray(x), np.asarray(y)), k
            hits += int(rb[2].sum())
            passes += int(rb[0].sum())
        assert np.array_equal(a.target, b.target) and np.array_equal(a.laps, b.laps)
        assert a.lap_times == b.lap_times
    assert passes > 15 and hits >= 1   # the comparison covered both outcomes
