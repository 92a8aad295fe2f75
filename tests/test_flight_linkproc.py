"""The link keeper (cfrace.flight.link.keeper): the drones' links live in a process of their own that
stops every flying drone when the flight loop's process dies (kill -9) or goes silent. Real cflib
over UDP against the simulated Crazyflies; the "loop" is a real subprocess."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from test_flight_core import _wait, hover_counts, served_fleet, track  # noqa: F401 (fixture)

LOOP = textwrap.dedent("""
    import sys, time
    from cfrace.flight.link.opener import link_factory
    uris, heartbeat, stop_log, counts = sys.argv[1].split(","), float(sys.argv[2]), sys.argv[3], int(sys.argv[4])
    make = link_factory(uris, heartbeat_s=heartbeat, stop_log=stop_log, estop_watchdog=sys.argv[5] == "1")
    links = [make(i, u) for i, u in enumerate(uris)]
    for link in links:
        link.connect(10.0)
        link.setup()
    print("flying", flush=True)
    while True:                      # a 100 Hz loop streaming setpoints until it is killed
        for link in links:
            link.send(0.0, 0.0, 0.0, counts)
        time.sleep(0.01)
""")


@pytest.fixture()
def served(track):
    yield from served_fleet(track, True)


def _start_loop(server, fleet, tmp_path, heartbeat_s: float = 0.1, uris=None, estop_watchdog: bool = False):
    stop_log = tmp_path / "stops.jsonl"
    proc = subprocess.Popen([sys.executable, "-c", LOOP, ",".join(uris or server.uris), str(heartbeat_s), str(stop_log),
                             str(hover_counts(fleet)), "1" if estop_watchdog else "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "flying", proc.stderr.read()
    assert _wait(lambda: all(fleet.status(i)["thrust"] > 0.0 for i in range(2)), 5.0)
    return proc, stop_log


def _stops(path, timeout=3.0) -> list[dict]:
    assert _wait(lambda: path.exists() and len(path.read_text().splitlines()) >= 2, timeout)
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_kill_9_of_the_loop_stops_every_drone_at_once(served, tmp_path):
    """The keeper wakes on the pipe's end (loop_gone), not on its 0.1 s heartbeat: well under 50 ms on a
    quiet machine; the bound below leaves a loaded CI VM's scheduling to the reason, which is exact."""
    fleet, server = served
    proc, stop_log = _start_loop(server, fleet, tmp_path)
    t_kill = time.monotonic()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    stops = _stops(stop_log)
    assert sorted(s["drone"] for s in stops) == [0, 1]
    for s in stops:
        assert s["why"] == "loop_gone" and s["was_flying"]    # the pipe's end, before any heartbeat
        assert 0.0 <= s["t_mono"] - t_kill < 1.0, s           # timestamped where sent
    assert _wait(lambda: all(fleet.status(i)["thrust"] == 0.0 and not fleet.status(i)["armed"] for i in range(2)))


def test_a_hung_loop_is_stopped_after_the_heartbeat(served, tmp_path):
    fleet, server = served
    proc, stop_log = _start_loop(server, fleet, tmp_path, heartbeat_s=0.1)
    try:
        t_hang = time.monotonic()
        os.kill(proc.pid, signal.SIGSTOP)                     # alive, pipe open, silent
        stops = _stops(stop_log)
        for s in stops:
            # never before 0.1 s of silence (the keeper's own clock), and soon after it (a loose bound:
            # the keeper's wake-up on a loaded machine)
            assert s["why"] == "heartbeat" and s["since_loop_s"] >= 0.1, s
            assert s["t_mono"] - t_hang < 1.0, s
        assert _wait(lambda: all(fleet.status(i)["thrust"] == 0.0 for i in range(2)))
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()


@pytest.mark.parametrize("watchdog", [True, False])
def test_a_lost_link_cuts_its_drones_motors_after_1_s_with_the_estop_watchdog(served, tmp_path, watchdog):
    """With estop_watchdog the keeper feeds every flying drone's emergency-stop watchdog: the drone
    whose link is cut (a UDP relay that drops everything) cuts its own motors 1 s after the last
    feed, while the other, still fed, flies on; without it the cut drone is only levelled (0.5 s)."""
    from cfrace.rehearsal.faults import UdpCutRelay

    fleet, server = served
    relay = UdpCutRelay(server.ports[0])
    proc, _ = _start_loop(server, fleet, tmp_path, heartbeat_s=0.5, uris=[relay.uri, server.uris[1]],
                          estop_watchdog=watchdog)
    try:
        time.sleep(0.3)
        relay.cut()
        t_cut = fleet.time
        if watchdog:
            assert _wait(lambda: fleet.status(0)["emergency_stopped"], 3.0)
            assert 0.85 <= fleet.time - t_cut <= 1.3, fleet.time - t_cut
            assert fleet.status(0)["emergency_reason"] == "emergency-stop watchdog"
        else:
            assert _wait(lambda: fleet.status(0)["watchdog"] == "level", 3.0)
            time.sleep(0.7)
            assert not fleet.status(0)["emergency_stopped"]
        assert not fleet.status(1)["emergency_stopped"] and fleet.status(1)["thrust"] > 0.0
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        relay.close()


def test_a_locked_drone_is_refused_at_set_up_with_one_line(served):
    """A drone whose firmware is locked by an emergency stop (e.g. the watchdog after a flight with
    --estop-watchdog) cannot be armed: set-up says so and what to do, before anything is sent."""
    from cfrace.errors import LinkError
    from cfrace.flight.link.keeper_client import LinkKeeper

    fleet, server = served
    fleet.emergency_stop(0, "emergency-stop watchdog")
    keeper = LinkKeeper(server.uris[:1], heartbeat_s=0.5)
    link = keeper.link(0)
    try:
        link.connect(10.0)
        with pytest.raises(LinkError, match="locked by an emergency stop.*restart it"):
            link.setup()
        assert fleet.status(0)["setpoints_received"] == 0
    finally:
        link.close()


def test_the_heartbeat_watches_setpoint_streams_not_the_high_level_commander(served, tmp_path):
    """A drone the firmware's high-level commander flies (the hover before a race, a landing) holds
    itself: a silent loop does not get it stopped (the real-time hover start was stopped by the
    heartbeat right after its take-off); once the loop streams setpoints, a silence stops it."""
    from cfrace.flight.link.keeper_client import LinkKeeper

    fleet, server = served
    stop_log = tmp_path / "stops.jsonl"
    keeper = LinkKeeper(server.uris[:1], heartbeat_s=0.1, stop_log=stop_log)
    link = keeper.link(0)
    try:
        link.connect(10.0)
        link.setup()
        link.high_level("takeoff", height=0.5, yaw=None, duration=2.0)
        time.sleep(0.5)                                  # silent for 5 heartbeats: the firmware flies it
        assert not stop_log.exists() or not stop_log.read_text().strip()
        for _ in range(10):
            link.send(0.0, 0.0, 0.0, hover_counts(fleet))
            time.sleep(0.01)
        stops = _stops_one(stop_log)
        assert stops[0]["why"] == "heartbeat" and stops[0]["was_flying"]
    finally:
        link.close()


def _stops_one(path, timeout=3.0) -> list[dict]:
    assert _wait(lambda: path.exists() and path.read_text().strip(), timeout)
    return [json.loads(line) for line in path.read_text().splitlines()]
