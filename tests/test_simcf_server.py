"""SimCrazyflieServer without cflib: raw UDP, pose stream, lockstep mode, errors, serve()."""

import socket
import struct
import threading
import time

import numpy as np
import pytest

from cfrace.errors import ConfigError, LinkError, MocapError
from cfrace.simcf import crtp
from cfrace.simcf.firmware import SimFleet
from cfrace.simcf.poses import PoseSubscriber, decode_frame, encode_frame
from cfrace.simcf.server import SimCrazyflieServer, serve


@pytest.fixture(scope="module")
def fleet():
    return SimFleet("complex", "cf2x_paper", 2, arming_required=False)


def udp_client(port):
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.settimeout(1.0)
    s.connect(("127.0.0.1", port))
    return s


def test_raw_udp_roundtrip_and_counters(fleet):
    with SimCrazyflieServer(fleet, base_port=0, realtime=False) as server:
        assert server.uris == [f"udp://127.0.0.1:{p}" for p in server.ports] and len(set(server.ports)) == 2
        c = udp_client(server.ports[1])
        c.send(b"\xff")                                           # cflib's scan probe
        assert c.recv(64)
        c.send(crtp.packet(crtp.LINK, 0, b"hello"))
        assert c.recv(64) == crtp.packet(crtp.LINK, 0, b"hello")
        c.send(crtp.packet(crtp.COMMANDER, 0, struct.pack("<fffH", 0, 0, 0, 0)))
        assert wait(lambda: fleet.status(1)["setpoints_received"] >= 1)
        st = server.stats()[1]
        assert st["rx"] == 3 and st["tx"] == 2 and st["setpoints"] == 1 and server.stats()[0]["rx"] == 0
        c.close()


def test_log_blocks_churn_in_real_time():
    """Blocks created, started and deleted at a high rate while the clock thread sends log data:
    data flows and no packet handling fails."""
    f = SimFleet("lemniscate", "cf2x_paper", 1)
    with SimCrazyflieServer(f, base_port=0) as server:
        c = udp_client(server.ports[0])
        c.settimeout(0.0)
        op = struct.pack("<BH", 0x07, 2)                         # stateEstimate.z as float
        for k in range(300):
            bid = k % 5
            c.send(crtp.packet(crtp.LOG, 1, bytes([6, bid]) + op))
            c.send(crtp.packet(crtp.LOG, 1, bytes([3, bid, 1])))   # start, 10 ms
            c.send(crtp.packet(crtp.LOG, 1, bytes([2, (bid + 2) % 5])))
            time.sleep(0.001)
        time.sleep(0.05)
        data = []
        while True:
            try:
                data.append(c.recv(64))
            except BlockingIOError:
                break
        c.close()
    assert server.errors == 0
    assert any(d[0] == crtp.packet(crtp.LOG, 2)[0] for d in data)   # log data did flow


def test_lockstep_mode_does_not_advance_time(fleet):
    with SimCrazyflieServer(fleet, base_port=0, realtime=False):
        t0 = fleet.time
        time.sleep(0.1)
        assert fleet.time == t0
        fleet.advance(0.05)
        assert fleet.time == pytest.approx(t0 + 0.05)


def test_realtime_clock_follows_the_wall_clock():
    """Simulated time is the wall-clock time elapsed less what overruns dropped (sim_lag, counted): a
    loaded machine may overrun, so the test asserts the accounting, not this machine's speed. One clock
    tick adds at most MAX_CATCH_UP (some of it from before t0) in whole 2 ms steps; the sim trails the
    wall clock by the time since its last tick (a loose bound for a loaded VM's thread wake-ups)."""
    from cfrace.simcf.server import MAX_CATCH_UP

    f = SimFleet("lemniscate", "cf2x_paper", 2)
    with SimCrazyflieServer(f, base_port=0) as server:
        t0, lag0, w0 = f.time, server.sim_lag, time.monotonic()
        time.sleep(0.5)
        elapsed = time.monotonic() - w0
        simulated, lag = f.time - t0, server.sim_lag - lag0
    assert simulated <= elapsed + MAX_CATCH_UP + 0.002          # never ahead of the wall clock
    assert simulated + lag >= elapsed - 0.3                     # and follows it
    assert server.errors == 0


def test_pose_stream(fleet):
    with SimCrazyflieServer(fleet, base_port=0, realtime=False) as server:
        with PoseSubscriber(port=server.pose_port) as sub:
            t, bodies = sub.wait(2.0)
            t_ref, ref = server.poses()
            assert t == t_ref and list(bodies) == ["cf1", "cf2"]
            for name in ref:
                np.testing.assert_allclose(bodies[name][0], ref[name][0])
                np.testing.assert_allclose(bodies[name][1], ref[name][1])
    with PoseSubscriber(port=server.pose_port) as sub:               # server gone
        with pytest.raises(MocapError, match="no simulated poses"):
            sub.wait(0.3)


def test_frame_codec_rejects_garbage():
    frame = encode_frame(1.5, {"a": (np.arange(3.0), np.array([1.0, 0, 0, 0]))})
    t, b = decode_frame(frame)
    assert t == 1.5 and b["a"][0].tolist() == [0, 1, 2]
    for bad in (b"", b"XXXX" + frame[4:], frame[:-3]):
        with pytest.raises(ValueError):
            decode_frame(bad)


def test_refuses_non_loopback_and_busy_ports(fleet):
    with pytest.raises(ConfigError, match="127.0.0.1 only"):
        SimCrazyflieServer(fleet, host="0.0.0.0")
    busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    busy.bind(("127.0.0.1", 0))
    port = busy.getsockname()[1]
    try:
        with pytest.raises(LinkError, match=f"udp://127.0.0.1:{port} \\(drone cf1's port\\)"):
            SimCrazyflieServer(fleet, base_port=port).start()
    finally:
        busy.close()


def test_a_busy_pose_port_is_named(fleet):
    """`sim serve --port P` with P - 1 taken: the line says P - 1 is the pose port."""
    for _ in range(20):                      # a port P - 1 that is busy while P, P + 1 are free
        busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        busy.bind(("127.0.0.1", 0))
        port = busy.getsockname()[1]
        try:
            with pytest.raises(LinkError) as e:
                SimCrazyflieServer(fleet, base_port=port + 1).start()
        finally:
            busy.close()
        if f":{port} " in str(e.value):
            break
    assert str(e.value) == (f"simcf: cannot listen on udp://127.0.0.1:{port} (the ground-truth pose port, the "
                            f"first drone's port {port + 1} - 1): Address already in use")


def test_no_lag_warning_below_one_clock_tick(fleet):
    server = SimCrazyflieServer(fleet, base_port=0)
    server.overruns, server.sim_lag = 1, 0.004          # would print as "0.00 s"
    assert server.lag_warning() == ""
    server.overruns, server.sim_lag = 3, 0.25
    assert server.lag_warning() == "  warning: simulation fell behind real time by 0.25 s"


@pytest.mark.parametrize("reset", [False, True])
def test_after_a_flight_the_drones_stay_or_go_back_to_the_grid(reset):
    """A flight: a client arms drone 0 (over UDP) and it ends up 2 m away on the floor, motors off;
    once no client has sent anything for FLIGHT_OVER_S the drones are back on the grid with
    reset_after_flight, else they stay where the flight left them (as real drones do)."""
    from cfrace.simcf.server import FLIGHT_OVER_S

    fleet = SimFleet("lemniscate", "cf2x_paper", 2, obstacles=False, decks=())
    grid = fleet.state(0)["pos"].copy()
    told = []
    with SimCrazyflieServer(fleet, base_port=0, reset_after_flight=reset, on_reset=lambda: told.append(1)) as server:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as client:
            client.sendto(bytes([0xF3]), ("127.0.0.1", server.ports[0]))      # a null packet: a client is there
            fleet.arm(0, True)
            time.sleep(0.1)
            fleet.teleport(0, grid + (2.0, 0.0, 0.0))
            time.sleep(0.1)
            fleet.arm(0, False)
            time.sleep(FLIGHT_OVER_S + 0.5)
        moved = float(np.linalg.norm(fleet.state(0)["pos"][:2] - grid[:2]))
        assert (moved < 0.01, server.resets, told) == ((True, 1, [1]) if reset else (False, 0, []))
        assert not fleet.status(0)["armed"]


def test_serve_prints_uris_and_stops():
    lines = []
    stats = serve("lemniscate", 2, port=0, profile="cf2x_paper", duration=0.3, out=lines.append)
    text = "\n".join(lines)
    assert "cf1: udp://127.0.0.1:" in text and "cf2: udp://127.0.0.1:" in text and "poses" in text
    assert "after a flight: the drones stay where they landed" in text     # what a second flight meets
    lines.clear()
    serve("lemniscate", 2, port=0, profile="cf2x_paper", duration=0.2, reset_after_flight=True, out=lines.append)
    assert "after a flight: every drone back on the start grid" in "\n".join(lines)
    assert len(stats) == 2 and all(s["rx"] == 0 for s in stats)


def test_serve_stops_on_sigterm():
    import os
    import signal

    before = signal.getsignal(signal.SIGTERM)

    def term_once_handled():   # only once serve() has its handler: earlier, SIGTERM would end pytest
        t_end = time.monotonic() + 30.0
        while signal.getsignal(signal.SIGTERM) is before and time.monotonic() < t_end:
            time.sleep(0.01)
        time.sleep(0.3)
        if signal.getsignal(signal.SIGTERM) is not before:
            sent.append(time.monotonic())
            os.kill(os.getpid(), signal.SIGTERM)

    sent = []
    threading.Thread(target=term_once_handled, daemon=True).start()
    serve("lemniscate", 1, port=0, profile="cf2x_paper", out=lambda s: None)
    assert sent and time.monotonic() - sent[0] < 10.0      # stopped after the signal, not at a time-out
    assert signal.getsignal(signal.SIGTERM) is before      # and gave the old handler back


def wait(cond, timeout=2.0):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end and not cond():
        time.sleep(0.01)
    return cond()
