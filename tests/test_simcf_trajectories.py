"""Memories and high-level trajectories of the simulated Crazyflie through the REAL cflib client over
UDP (real time): what cflib's autonomous trajectory example does (upload a figure-8 of poly4d pieces
to the trajectory memory, define it, take off, start it, land), the memory list, info, read/write and
bounds errors, compressed trajectories, group masks across drones, and bad input. The references
the flights are checked against are evaluated here with numpy's polynomials and Bernstein
polynomials, not with the simulator's evaluator.
"""

import errno
import math
import struct
import threading
import time

import numpy as np
import pytest

cflib = pytest.importorskip("cflib")
import cflib.crtp  # noqa: E402
from cflib.crazyflie.log import LogConfig  # noqa: E402
from cflib.crazyflie.mem import CompressedSegment, CompressedStart, MemoryElement, Poly4D  # noqa: E402
from cflib.crazyflie.mem.deck_memory import SyncDeckMemoryManager  # noqa: E402
from cflib.crtp.crtpstack import CRTPPacket, CRTPPort  # noqa: E402
from cflib.utils.reset_estimator import reset_estimator  # noqa: E402
from numpy.polynomial import polynomial as npoly  # noqa: E402

from cfrace.simcf.firmware import SimFleet  # noqa: E402
from cfrace.simcf.server import SimCrazyflieServer  # noqa: E402
from cflibtools import connect, wait_for  # noqa: E402

cflib.crtp.init_drivers()

FIGURE8_PERIOD = 8.0   #: s
PIECES = 8


def figure8_pieces(a=0.6, b=0.3, period=FIGURE8_PERIOD, n=PIECES):
    """A figure-8 x = a sin(w t), y = b sin(2 w t) as n degree-7 pieces (least squares on each piece;
    z and yaw zero): [(duration, x coeffs, y coeffs)], starting at the origin."""
    w, d = 2.0 * math.pi / period, period / n
    out = []
    for k in range(n):
        tau = np.linspace(0.0, d, 50)
        t = k * d + tau
        out.append((d, npoly.polyfit(tau, a * np.sin(w * t), 7), npoly.polyfit(tau, b * np.sin(2 * w * t), 7)))
    return out


def as_float32(c):
    return np.asarray(c, np.float32).astype(np.float64)


def poly4d(duration, x, y, z=None, yaw=None):
    zero = [0.0] * 8
    return Poly4D(duration, Poly4D.Poly(list(x)), Poly4D.Poly(list(y)), Poly4D.Poly(list(z if z is not None else zero)),
                  Poly4D.Poly(list(yaw if yaw is not None else zero)))


def reference(pieces, tau):
    """The uploaded pieces (float32 coefficients, as stored) at trajectory time tau (s): (x, y)."""
    for d, x, y in pieces:
        if tau <= d:
            return npoly.polyval(tau, as_float32(x)), npoly.polyval(tau, as_float32(y))
        tau -= d
    d, x, y = pieces[-1]
    return npoly.polyval(d, as_float32(x)), npoly.polyval(d, as_float32(y))


class Recorder:
    """Ground truth (t_sim, pos) of drone i every 10 ms of wall time, on a thread."""

    def __init__(self, fleet, i):
        self.fleet, self.i, self.rows, self._stop = fleet, i, [], threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        name = self.fleet.body_names[self.i]
        while not self._stop.is_set():
            t, poses = self.fleet.poses()
            self.rows.append((t, poses[name][0].copy()))
            time.sleep(0.01)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


class Answers:
    """The drone's answers on the high-level commander port and its console text."""

    def __init__(self, cf):
        self.hl, self.console = [], ""
        cf.add_port_callback(CRTPPort.SETPOINT_HL, lambda pk: self.hl.append(bytes(pk.data)))
        cf.console.receivedChar.add_callback(self._text)

    def _text(self, text):
        self.console += text

    def last(self, command):
        """The return code of the last answer to ``command``."""
        codes = [a[3] for a in self.hl if a and a[0] == command]
        return codes[-1] if codes else None


def send_hl(cf, payload):
    pk = CRTPPacket()
    pk.port = CRTPPort.SETPOINT_HL
    pk.data = payload
    cf.send_packet(pk)


def upload(cf, elements, start_addr=0):
    mem = cf.mem.get_mems(MemoryElement.TYPE_TRAJ)[0]
    mem.trajectory = elements
    return mem.write_data_sync(start_addr=start_addr)


def fleet_and_server(drones=1, decks=("lighthouse",)):
    fleet = SimFleet("lemniscate", "cf2x_paper", drones, arming_required=True, decks=decks)
    return fleet, SimCrazyflieServer(fleet, base_port=0)


@pytest.mark.parametrize("controller", [1, 2], ids=["pid", "mellinger"])
def test_cflib_figure8_example_flies_its_polynomial(controller):
    """The logic of cflib's examples/autonomy/autonomous_sequence_high_level.py: upload, define,
    reset the estimator, arm, take off to 1 m, start relative to the hover point, land, stop; with
    the firmware's default PID controller and with the Mellinger controller that the example's
    activate_mellinger_controller selects (stabilizer.controller 2).

    The setpoints (logged through cflib, ctrltarget.x/y/z at 10 ms) are the uploaded polynomial from
    the hover point within 1 cm (one 10 ms control tick at 0.5 m/s). On this 1.2 m x 0.6 m figure
    flown in 8 s (a drone that hovered at the start would be 0.47 m RMS off):

    * PID: the position error alone makes a velocity (position_controller_pid.c, no feed-forward),
      so the drone follows about 0.4 s behind: between 0.1 and 0.3 m RMS (0.23 m measured);
    * Mellinger: the setpoint's velocity and acceleration feed forward (controller_mellinger.c),
      within 5 cm RMS (2.5 cm measured, most of it in the first second: the figure starts at
      0.47 m/s from a hover)."""
    pieces = figure8_pieces()
    duration = sum(d for d, _, _ in pieces)
    fleet, server = fleet_and_server()
    with server, connect(server.uris[0]) as scf:
        cf = scf.cf
        traj_mem = cf.mem.get_mems(MemoryElement.TYPE_TRAJ)
        assert len(traj_mem) == 1 and traj_mem[0].size == 4096
        cf.param.set_value("stabilizer.controller", str(controller))
        assert upload(cf, [poly4d(d, x, y) for d, x, y in pieces])
        cf.high_level_commander.define_trajectory(1, 0, len(pieces))
        reset_estimator(cf)
        cf.supervisor.send_arming_request(True)
        time.sleep(1.0)
        cf.high_level_commander.takeoff(1.0, 2.0, yaw=0.0)
        time.sleep(3.0)
        logged = []
        conf = LogConfig(name="setpoint", period_in_ms=10)
        for name in ("ctrltarget.x", "ctrltarget.y", "ctrltarget.z"):
            conf.add_variable(name, "float")
        conf.data_received_cb.add_callback(lambda ts, data, _: logged.append((ts / 1000.0, [
            data["ctrltarget.x"], data["ctrltarget.y"], data["ctrltarget.z"]])))
        cf.log.add_config(conf)
        conf.start()
        time.sleep(0.3)
        with Recorder(fleet, 0) as rec:
            cf.high_level_commander.start_trajectory(1, 1.0, relative_position=True)
            time.sleep(duration + 0.5)
        conf.stop()
        t0 = fleet._fw[0].planner.traj.t_begin          # the simulated time the drone started the trajectory
        cf.high_level_commander.land(0.0, 2.0)
        time.sleep(2.5)
        cf.high_level_commander.stop()
        assert wait_for(lambda: fleet.status(0)["thrust"] == fleet.idle_thrust(0), 1.0)
    before = [np.array(v) for t, v in logged if t < t0 - 0.02]
    assert before and before[-1][2] == pytest.approx(1.0)
    start = before[-1]                                    # the take-off's goal: where the figure starts
    sp_err = [np.linalg.norm(np.array(v) - (start + [*reference(pieces, t - t0), 0.0]))
              for t, v in logged if 0.0 <= t - t0 <= duration]
    assert len(sp_err) > 0.5 * duration / 0.01 and max(sp_err) < 0.01, max(sp_err)
    err, flown = [], []
    for t, pos in rec.rows:
        if 0.0 <= t - t0 <= duration:
            err.append(np.linalg.norm(pos - (start + [*reference(pieces, t - t0), 0.0])))
            flown.append(pos)
    flown = np.array(flown)
    assert len(err) > 0.5 * duration / 0.01
    rms = float(np.sqrt(np.mean(np.square(err))))
    print(f"figure-8, controller {controller}: setpoints within {max(sp_err) * 1000:.1f} mm, flown {rms:.3f} m RMS, max {max(err):.3f} m")
    if controller == 1:
        assert 0.1 < rms < 0.3, f"RMS {rms:.3f} m from the polynomial"
    else:
        assert rms < 0.05, f"RMS {rms:.3f} m from the polynomial"
    assert np.ptp(flown[:, 0]) == pytest.approx(1.2, abs=0.2) and np.ptp(flown[:, 1]) == pytest.approx(0.6, abs=0.15)
    assert fleet.state(0)["pos"][2] < 0.05 and not fleet.status(0)["crashed"]


def _mem_answer(mem, ok_caller, failed_caller, send, ok_value, timeout=2.0):
    """Send a memory request and wait for cflib's success or failure callback of this memory:
    ok_value(args) on success, None (read) / False (write) on failure."""
    done, out = threading.Event(), {}

    def answer(value):
        def cb(m, *args):
            if m.id == mem.id:
                out["v"] = value(args) if callable(value) else value
                done.set()
        return cb
    ok, failed = answer(ok_value), answer(None if ok_value is not True else False)
    ok_caller.add_callback(ok)
    failed_caller.add_callback(failed)
    try:
        send()
        assert done.wait(timeout), "no answer from the memory"
        return out["v"]
    finally:
        ok_caller.remove_callback(ok)
        failed_caller.remove_callback(failed)


def mem_read(cf, mem, addr, n):
    """Raw read through cflib's memory handler: the data, or None when the drone answered a failure."""
    return _mem_answer(mem, cf.mem.mem_read_cb, cf.mem.mem_read_failed_cb, lambda: cf.mem.read(mem, addr, n),
                       lambda args: bytes(args[1]))


def mem_write(cf, mem, addr, data) -> bool:
    return _mem_answer(mem, cf.mem.mem_write_cb, cf.mem.mem_write_failed_cb,
                       lambda: cf.mem.write(mem, addr, bytearray(data), flush_queue=True), True)


def test_memories_list_info_read_write_and_bounds():
    fleet, server = fleet_and_server(decks=("lighthouse", "flow", "ledring"))
    with server, connect(server.uris[0]) as scf:
        cf = scf.cf
        assert cf.mem.nbr_of_mems == 5
        (traj,) = cf.mem.get_mems(MemoryElement.TYPE_TRAJ)
        (tester,) = cf.mem.get_mems(MemoryElement.TYPE_MEMORY_TESTER)
        (decks,) = cf.mem.get_mems(MemoryElement.TYPE_DECK_MEMORY)
        (led,) = cf.mem.get_mems(MemoryElement.TYPE_DRIVER_LED)
        (timing,) = cf.mem.get_mems(MemoryElement.TYPE_DRIVER_LEDTIMING)
        assert (traj.size, tester.size, led.size, timing.size) == (4096, 0x1000, 24, 44)
        # trajectory memory: a write and read that end at its last byte succeed, one byte further fails (EIO)
        assert mem_write(cf, traj, 4080, bytes(range(16)))
        assert mem_read(cf, traj, 4080, 16) == bytes(range(16))
        assert bytes(fleet._fw[0].planner.memory[4080:]) == bytes(range(16))
        assert mem_read(cf, traj, 4081, 16) is None
        assert not mem_write(cf, traj, 4081, bytes(16))
        traj.trajectory = [poly4d(1.0, [0.0] * 8, [0.0] * 8)] * 32            # 32 x 132 bytes > 4096
        assert not traj.write_data_sync()
        # the memory tester: each address's low byte
        assert mem_read(cf, tester, 0x1F0, 20) == bytes((0x1F0 + k) & 0xFF for k in range(20))
        # deck memory: the Lighthouse deck's (the Flow deck and the LED ring have none)
        infos = SyncDeckMemoryManager(decks).query_decks()
        assert list(infos) == [0] and infos[0].name == "bcLighthouse4" and infos[0].is_started
        assert not infos[0].supports_read and not infos[0].supports_write
        # LED ring: cflib's LED driver memory writes RGB565 for 12 LEDs; reads back; past the end: EIO
        led.leds[0].set(255, 0, 0)
        led.leds[11].set(0, 0, 255)
        written = threading.Event()
        led.write_data(lambda m, a: written.set())
        assert written.wait(2.0)
        colours = mem_read(cf, led, 0, 24)
        assert colours[:2] == bytes([0xF8, 0x00]) and colours[22:] == bytes([0x00, 0x1F]) and colours[2:22] == bytes(20)
        assert mem_read(cf, led, 20, 5) is None and mem_read(cf, timing, 0, 24) == bytes(24)
        assert mem_read(cf, timing, 30, 11) is None                           # 40 bytes of timings
        assert cf.param.get_value("deck.bcLedRing") == "1"


def bernstein(points, s):
    n = len(points) - 1
    return sum(math.comb(n, i) * (1 - s) ** (n - i) * s ** i * p for i, p in enumerate(points))


def test_compressed_trajectory_flies_its_bezier_pieces():
    """cflib's CompressedStart/CompressedSegment (mm and 1/10 deg): a cubic then a 7th-order Bezier piece
    in x, a linear one in y, constant z, flown relative to the hover point. The setpoints are the
    Bezier curves of the stored control points within 1 cm; a time scale or reversed: ENOEXEC."""
    segments = [(3.0, [0.1, 0.3, 0.4], [0.2], [], []),
                (3.0, [0.4, 0.3, 0.2, 0.1, 0.0, -0.1, -0.1], [0.1], [], [])]
    fleet, server = fleet_and_server()
    with server, connect(server.uris[0]) as scf:
        cf = scf.cf
        answers = Answers(cf)
        elements = [CompressedStart(0.0, 0.0, 0.0, 0.0)] + [CompressedSegment(*s) for s in segments]
        assert upload(cf, elements, start_addr=132)
        cf.high_level_commander.define_trajectory(4, 132, len(segments), type=1)
        cf.supervisor.send_arming_request(True)
        time.sleep(1.0)
        cf.high_level_commander.takeoff(0.8, 2.0)
        time.sleep(2.5)
        cf.high_level_commander.start_trajectory(4, 2.0, relative_position=True)
        cf.high_level_commander.start_trajectory(4, 1.0, relative_position=True, reversed=True)
        assert wait_for(lambda: len([a for a in answers.hl if a[0] == 13]) == 2, 1.0)
        assert [a[3] for a in answers.hl if a[0] == 13] == [errno.ENOEXEC, errno.ENOEXEC]
        assert fleet.status(0)["high_level"] == "flying" and fleet.state(0)["pos"][2] == pytest.approx(0.8, abs=0.1)
        start = np.array([fleet.log_values(0)[f"ctrltarget.{k}"] for k in "xyz"])
        samples = []
        cf.high_level_commander.start_trajectory(4, 1.0, relative_position=True)
        t_end = time.monotonic() + 6.5
        while time.monotonic() < t_end:
            lv = fleet.log_values(0)
            samples.append((fleet.time, np.array([lv[f"ctrltarget.{k}"] for k in "xyz"])))
            time.sleep(0.02)
        t0 = fleet._fw[0].planner.traj.t_begin
        assert answers.last(13) == 0
        cf.high_level_commander.land(0.0, 2.0)
        time.sleep(2.5)
    stored = [[int(v * 1000) / 1000 for v in seg[1]] for seg in segments]        # mm, as cflib encodes them
    x_pts = [[0.0] + stored[0], [stored[0][-1]] + stored[1]]
    y_pts = [[0.0, 0.2], [0.2, 0.1]]
    worst, checked = 0.0, 0
    for t, sp in samples:
        tau = t - t0
        if not 0.02 <= tau <= 6.0:
            continue
        k = 0 if tau < 3.0 else 1
        s = (tau - 3.0 * k) / 3.0
        ref = start + [bernstein(x_pts[k], s), bernstein(y_pts[k], s), 0.0]
        worst = max(worst, float(np.linalg.norm(sp - ref)))
        checked += 1
    assert checked > 100 and worst < 0.01, worst
    end = [tp for tp in samples if tp[0] - t0 > 6.1]
    assert end and np.allclose(end[-1][1], start + [-0.1, 0.1, 0.0], atol=1e-3)   # holds the last point


RISE = [0.0, 0.0, 0.225, -0.075, 0.0, 0.0, 0.0, 0.0]   #: z(t) = 0.3 m x smoothstep(t / 2 s): 0.3 m up in 2 s


def test_group_masks_and_bad_input_across_three_drones():
    """hlCommander.groupmask 1, 2 and 3: a start for group 1 moves drones 0 and 2 only. Bad input to
    drone 1 gets the firmware's answer and one console line, and the others fly on: an unknown
    trajectory id (0, ignored), an id past 30 (ENOEXEC), a definition past the memory's end (0, then
    its start ENOEXEC), a short packet (ENOEXEC), NaN coefficients (the commander disables itself)."""
    fleet, server = fleet_and_server(drones=3)
    with server, connect(server.uris[0]) as s0, connect(server.uris[1]) as s1, connect(server.uris[2]) as s2:
        cfs = [s0.cf, s1.cf, s2.cf]
        answers = [Answers(cf) for cf in cfs]
        for k, cf in enumerate(cfs):
            assert upload(cf, [poly4d(2.0, [0.0] * 8, [0.0] * 8, z=RISE)])
            cf.high_level_commander.define_trajectory(1, 0, 1)
            cf.param.set_value("hlCommander.groupmask", str([1, 2, 3][k]))
            cf.supervisor.send_arming_request(True)
        assert wait_for(lambda: [fleet.get_param(k, "hlCommander.groupmask") for k in range(3)] == [1, 2, 3], 2.0)
        time.sleep(0.5)
        for cf in cfs:
            cf.high_level_commander.takeoff(0.8, 2.0)
        time.sleep(3.0)
        for cf in cfs:                                   # as a broadcast would: every drone gets it
            cf.high_level_commander.start_trajectory(1, 1.0, relative_position=True, group_mask=1)
        time.sleep(2.5)
        z = [fleet.state(k)["pos"][2] for k in range(3)]
        assert z[0] == pytest.approx(1.1, abs=0.1) and z[2] == pytest.approx(1.1, abs=0.1), z
        assert z[1] == pytest.approx(0.8, abs=0.1), z
        # bad input to drone 1 while drones 0 and 2 hover
        hl1, a1 = cfs[1].high_level_commander, answers[1]
        mark = len(a1.hl)
        hl1.start_trajectory(9, 1.0)                                  # never defined
        hl1.define_trajectory(31, 0, 1)                               # ids are 0-30
        hl1.define_trajectory(3, 4000, 2)                             # 4000 + 2 x 132 > 4096
        assert wait_for(lambda: len([a for a in a1.hl[mark:] if a[0] == 6]) == 2, 1.0)
        assert [a[3] for a in a1.hl[mark:] if a[0] == 6] == [errno.ENOEXEC, 0]
        hl1.start_trajectory(3, 1.0)
        send_hl(cfs[1], bytes([13, 0, 0]))                            # a start_trajectory cut short
        assert wait_for(lambda: len([a for a in a1.hl[mark:] if a[0] == 13]) == 3, 1.0)
        assert [a[3] for a in a1.hl[mark:] if a[0] == 13] == [0, errno.ENOEXEC, errno.ENOEXEC]
        assert wait_for(lambda: all(w in a1.console for w in ("trajectory 9 is not defined", "no trajectory id 31",
                                                              "reach past", "not inside the trajectory memory",
                                                              "bad length")), 1.0), a1.console
        assert fleet.status(1)["high_level"] == "flying" and fleet.state(1)["pos"][2] == pytest.approx(0.8, abs=0.1)
        nan = [float("nan")] + [0.0] * 7
        assert upload(cfs[1], [poly4d(2.0, nan, [0.0] * 8)], start_addr=1320)
        hl1.define_trajectory(2, 1320, 1)
        hl1.start_trajectory(2, 1.0, group_mask=2)
        assert wait_for(lambda: fleet.status(1)["high_level"] == "disabled", 1.0)
        assert wait_for(lambda: "evaluates to NaN" in a1.console, 1.0) and a1.console.count("evaluates to NaN") == 1
        time.sleep(1.0)
        for k in (0, 2):                                              # the others fly on
            st = fleet.status(k)
            assert st["high_level"] == "flying" and not st["crashed"] and st["watchdog"] == "ok"
            assert fleet.state(k)["pos"][2] == pytest.approx(1.1, abs=0.1)
        assert fleet.status(1)["watchdog"] != "ok"                    # drone 1's last setpoint ages out
        for cf in cfs:
            cf.high_level_commander.land(0.0, 2.0, group_mask=0b101)
        time.sleep(2.5)
        assert fleet.state(0)["pos"][2] < 0.05 and fleet.state(2)["pos"][2] < 0.05


# ---------------------------------------------------------------- the planner's rules, no UDP
from cfrace.simcf.planner import Goal, Planner  # noqa: E402

PX = [0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0]       #: x = t + t^2
PY = [0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]       #: y = t / 2
PYAW = [0.0, 0.3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]     #: yaw = 0.3 t


def planner_with_piece(duration=1.0):
    p = Planner()
    p.memory[0:132] = struct.pack("<33f", *PX, *PY, *[0.0] * 8, *PYAW, duration)
    assert p.define_trajectory(0, 1, 0, 0, 1) == 0
    return p


def test_time_scale_reversed_and_relative_yaw_as_the_firmware():
    at_rest = Goal(np.array([1.0, 2.0, 3.0]), np.zeros(3), np.zeros(3), math.pi / 2, 0.0)
    p = planner_with_piece()
    assert p.start_trajectory(at_rest, 0, 2.0, False, False, False, t=10.0) == 0       # twice as slow
    g = p.evaluate(10.0 + 2 * 0.4)
    assert g.pos[:2] == pytest.approx([0.4 + 0.16, 0.2]) and g.vel[:2] == pytest.approx([(1 + 0.8) / 2, 0.25])
    assert g.yaw == pytest.approx(0.12) and g.yaw_rate == pytest.approx(0.15)
    end = p.evaluate(13.0)
    assert end.pos[:2] == pytest.approx([2.0, 0.5]) and not end.vel.any() and p.finished(13.0)
    p.start_trajectory(at_rest, 0, 1.0, True, False, True, t=20.0)                      # reversed, relative
    g = p.evaluate(20.25)
    assert g.pos == pytest.approx([1.0 + 0.75 + 0.5625 - 2.0, 2.0 + 0.375 - 0.5, 3.0])  # starts at the end point
    assert g.vel[:2] == pytest.approx([-(1 + 1.5), -0.5])
    assert p.evaluate(22.0).pos == pytest.approx([1.0 - 2.0, 2.0 - 0.5, 3.0])           # holds the first point
    p.start_trajectory(at_rest, 0, 1.0, True, True, False, t=30.0)                      # rotated to the yaw
    g = p.evaluate(30.5)
    assert g.pos == pytest.approx([1.0 - 0.25, 2.0 + 0.75, 3.0]) and g.vel[:2] == pytest.approx([-0.5, 2.0])
    assert g.yaw == pytest.approx(math.pi / 2 + 0.15)


def test_spiral_flies_an_arc():
    f = SimFleet("lemniscate", "cf2x_paper", 1, arming_required=True)
    f.arm(0, True)
    f.advance(0.5)
    assert f.high_level(0, "takeoff", height=0.8, yaw=0.0, duration=2.0) == 0
    f.advance(3.0)
    start = np.array([f.log_values(0)[f"ctrltarget.{k}"] for k in "xyz"])
    assert f.high_level(0, "spiral", sideways=False, clockwise=False, angle=math.pi / 2, r0=0.5, rf=0.5,
                        ascent=0.2, duration=4.0) == 0
    centre = start[:2] + [0.0, 0.5]                   # facing +x, turning left: the centre is on the left
    plan, radius = f._fw[0].planner, []
    for k in range(400):
        f.advance(0.01)
        g = plan.traj.eval(f.time)
        radius.append(np.linalg.norm(g.pos[:2] - centre))
    assert np.abs(np.array(radius) - 0.5).max() < 0.01
    assert g.pos == pytest.approx([start[0] + 0.5, start[1] + 0.5, start[2] + 0.2], abs=1e-6)
    assert g.yaw == pytest.approx(math.pi / 2)
    f.advance(1.0)
    assert f.state(0)["pos"] == pytest.approx(g.pos, abs=0.05)
    assert f.high_level(0, "spiral", sideways=True, clockwise=True, angle=7.0, r0=-1.0, rf=0.3, ascent=0.0,
                        duration=3.0) == 0
    assert any("saturated" in e for e in f.drain_events(0))
