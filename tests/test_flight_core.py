"""Flight core pieces: link conventions (direct and real cflib over UDP), clocks, race progress,
the observation agreement with the simulator/env, and the loop's race logic."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
import torch

from cfrace.contract.actions import thrust_to_counts
from cfrace.errors import LinkError
from cfrace.flight.loop.clock import LockstepClock, RealClock
from cfrace.flight.link.protocol import DirectSimLink, RecordingLink, cflib_setpoint_args, packet_values
from cfrace.flight.link.opener import open_link
from cfrace.flight.loop.gate_progress import FastRaceProgress
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
    assert thrust_to_counts(1e3, curve) == int(curve.counts[-1])  # clamped to the curve (<= 65535)
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


def served_fleet(track, realtime: bool):
    """(fleet, server): airborne simulated drones served over UDP, stopped after the test."""
    from cfrace.simcf.server import SimCrazyflieServer

    fleet = airborne_fleet(track)
    server = SimCrazyflieServer(fleet, base_port=0, realtime=realtime).start()
    yield fleet, server
    server.stop()


@pytest.fixture()
def udp_fleet(track):
    yield from served_fleet(track, False)


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
        assert time.monotonic() - t0 < 10.0       # gave up at its 0.5 s time-out (a loose bound: a loaded VM)


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


def test_real_clock_final_wait_yields_without_sleeping():
    """Real time: after the warm-up the clock waits out the last 0.1 ms with sched_yield, never with
    time.sleep(0) (which arms a timer per call: ticks started up to 0.1 ms late on a VM)."""
    sleeps = []

    def sleep(s):
        sleeps.append(s)
        time.sleep(s)

    clock = RealClock(0.01, sleep=sleep)
    clock.start()
    for _ in range(6):
        clock.wait_next(lambda: None, 0.0015)
    assert 0 not in sleeps and len(sleeps) >= 3            # real sleeps up to the lead (a stalled tick: none), no sleep(0)


def test_real_clock_warms_up_from_lead_ahead_until_just_before_the_deadline_and_never_when_late():
    ft = FakeTime()
    clock = RealClock(0.01, perf=ft.perf, sleep=ft.sleep, yield_cpu=lambda: ft.sleep(0))
    clock.start()
    calls = []

    def before():                              # a warm-up call that takes 0.3 ms
        calls.append((clock.next_k, round(ft.now - clock.t0, 6)))
        ft.now += 0.0003

    clock.wait_next(before, 0.001)             # tick 0 is due at once: no time to warm up
    ft.now += 0.002
    n_sleeps = len(ft.sleeps)
    t1 = clock.wait_next(before, 0.001)
    # from the deadline minus the lead (plus the sleep's overshoot), while one more 0.3-ms call
    # still ends 0.1 ms (WARM_GUARD_S) before the deadline: at 9.1 and 9.4 ms, not at 9.7 ms
    assert calls == [(1, 0.0091), (1, 0.0094)]
    # then no more sleeping through: only the yield (here a sleep(0), overshooting by 0.1 ms) up to the deadline
    assert ft.sleeps[n_sleeps] == pytest.approx(0.007) and set(ft.sleeps[n_sleeps + 1:]) == {0}
    assert t1.k == 1 and 0.0 <= t1.late_s <= 0.0001
    ft.now += 0.0095                           # work ran into the lead window: no warm-up
    t2 = clock.wait_next(before, 0.001)
    assert len(calls) == 2 and t2.k == 2


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
    paths = [gate_path(track, 5.0, laps=2), gate_path(track, 8.0, laps=2, lateral=0.45),
             gate_path(track, 6.0, lateral=0.55)]
    for trial in range(4):   # random walks around the gates: passes, misses and frame hits
        start = track.gate_array()[trial, :3] + rng.normal(0, 0.3, 3)
        paths.append(start + np.cumsum(rng.normal(0, 0.08, (300, 3)), axis=0))
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


# ---------------------------------------------------------------------------------------------- observations

def test_flight_observations_agree_with_the_simulator_and_env(track):
    """The same states give the same observations in the env (build_observations on the simulator
    state) and in the flight loop (ObservationBuilder on estimates); with zero-noise mocap through
    the estimator, positions/attitude/gates agree to float32 and velocity to the filter's lag."""
    from cfrace.drone import load_profile
    from cfrace.contract.observations import LAYOUTS, build_observations
    from cfrace.flight.mocap.estimation import Estimate, PoseEstimator
    from cfrace.flight.loop.flight_loop import ObservationBuilder
    from cfrace.flight.mocap.sources import MocapFrame, Pose
    from cfrace.rehearsal.hold_policy import hold_policy_layers
    from cfrace.sim.simulator import Simulator

    profile = load_profile(PROFILE)
    sim = Simulator(track, profile, worlds=1, drones=2, obstacles=False)
    start = torch.tensor([[[1.3, 2.2, 0.5], [1.7, 2.2, 0.6]]])
    yaw = math.pi / 2                     # facing gate 0
    quat = torch.tensor([[[math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)]] * 2])
    sim.reset(torch.tensor([0]), start, quat=quat)
    layout = LAYOUTS["race42"]
    # drone 0 seeks gate 0 (passes it), drone 1 holds its place (they would collide otherwise)
    wb = [hold_policy_layers(layout, profile.max_thrust_weights, profile.max_rates_deg, seek=s) for s in (3.0, 0.0)]
    corners = torch.as_tensor(track.gate_corners(), dtype=torch.float32)
    builder = ObservationBuilder(track.gate_corners())
    est = PoseEstimator(["cf1", "cf2"], stale_after_s=0.15)
    progress = FastRaceProgress(track.gate_array(), 2)
    from cfrace.contract.actions import action_to_command

    worst = np.zeros(3)
    for k in range(200):                  # 2 s at 100 Hz (gate 0 is passed at ~1.2 s)
        pos, vel, rot = sim.pos[0], sim.vel[0], sim.rot()[0]
        env_obs = build_observations(pos, vel, rot, sim.target[0], corners, layout)     # (2, 42)
        frame = MocapFrame(k * 0.01, {n: Pose(pos[i].double().numpy(), sim.quat[0, i].double().numpy())
                                      for i, n in enumerate(["cf1", "cf2"])}, k + 1)
        e = est.update(frame, k * 0.01)
        progress.update(k * 0.01, np.stack([e["cf1"].pos, e["cf2"].pos]))
        assert progress.target.tolist() == sim.target[0].tolist(), k
        exact = [Estimate(pos[i].double().numpy(), vel[i].double().numpy(), rot[i].double().numpy(),
                          None, 0.0, 0.0, True) for i in range(2)]
        for i, name in enumerate(["cf1", "cf2"]):
            o_exact = builder(layout, exact[i], int(progress.target[i]), exact[1 - i])
            assert np.array_equal(o_exact, env_obs[i].numpy())          # same function, same inputs
            o_flight = builder(layout, e[name], int(progress.target[i]), e[["cf1", "cf2"][1 - i]])
            d = np.abs(o_flight - env_obs[i].numpy())
            if k > 5:   # after the velocity filter settled
                worst = np.maximum(worst, [d[3:12].max(), d[12:36].max(), np.r_[d[:3], d[39:42]].max()])
        act = torch.stack([torch.as_tensor(env_obs[i].numpy() @ w.T + b) for i, (w, b) in enumerate(wb)]).clamp(-1, 1)
        thrust, rates = action_to_command(act, profile.mass, profile.max_thrust_weights, profile.max_rates_deg)
        sim.step(thrust[None].float(), rates[None].float(), substeps=5)
    assert worst[0] < 1e-5 and worst[1] < 1e-5      # attitude and gate corners
    assert worst[2] < 0.15                          # velocity terms: finite-difference filter lag, m/s
    assert sim.gates_passed[0, 0] >= 1 and not sim.crashed[0].any()   # it flew through gate 0 (target switched)


# ---------------------------------------------------------------------------------------------- loop logic

class ScriptedMocap:
    """Frames from precomputed paths (one row per loop tick), both bodies level."""

    name = "scripted"

    def __init__(self, paths: dict, clock):
        self.paths, self.clock, self.seq = paths, clock, 0

    def read(self, timeout_s=0.0):
        k = int(round(self.clock.now() / self.clock.dt))
        from cfrace.flight.mocap.sources import MocapFrame, Pose

        self.seq += 1
        poses = {b: Pose(p[min(k, len(p) - 1)], np.array([1.0, 0, 0, 0])) for b, p in self.paths.items()}
        return MocapFrame(k * self.clock.dt, poses, self.seq)

    def close(self):
        pass


class CountingPolicy:
    def __init__(self, dim):
        self.calls, self.dim = 0, dim

    def __call__(self, obs):
        assert obs.shape == (1, self.dim) and obs.dtype == np.float32
        self.calls += 1
        self.last = obs
        return np.array([[-0.2, 0.0, 0.0, 0.0]], np.float32)


def make_loop(track, paths, *, laps=1, timeout_s=30.0, clock=None, safety=None):
    from cfrace.drone import load_profile
    from cfrace.contract.observations import LAYOUTS
    from cfrace.flight.config import SafetyConfig
    from cfrace.flight.mocap.estimation import PoseEstimator
    from cfrace.flight.loop.flight_loop import FlownDrone, FlightLoop, ObservationBuilder
    from cfrace.flight.safety.check import Fence

    clock = clock or LockstepClock(0.01)
    prof = load_profile(PROFILE)
    safety = safety or SafetyConfig(speed_max_mps=50.0, floor_grace_s=3600.0)
    drones = []
    for phase, (name, body, lay) in enumerate((("ego", "cf1", "race42"), ("opp", "cf2", "solo36"))):
        link = RecordingLink(f"null://{name}", clock=clock.now)
        link.connect()
        meta = {"max_thrust_weights": 3.15, "max_rates_deg": [100.0, 100.0, 200.0], "method": name}
        drones.append(FlownDrone(name, body, CountingPolicy(LAYOUTS[lay].dim), LAYOUTS[lay], link, meta, prof.mass,
                            prof.thrust_curve, decimation=2, phase=phase))
    mocap = ScriptedMocap(paths, clock)
    loop = FlightLoop(drones=drones, mocap=mocap, estimator=PoseEstimator(["cf1", "cf2"], max_speed_mps=50.0),
                      progress=FastRaceProgress(track.gate_array(), 2), obs_builder=ObservationBuilder(track.gate_corners()),
                      clock=clock, fence=Fence.from_track(track, 5.0), safety_cfg=safety, laps=laps,
                      timeout_s=timeout_s, link_clock=clock.now, consistency=False)   # scripted poses
    for d in drones:   # the scripted paths never answer on links: keep them heard
        d.link.quality.last_rx = float("inf")
    return loop


def test_policies_are_warmed_before_the_first_tick_only_with_a_warm_up_window(track):
    """The first ticks have no warm-up window before them: with one (prewarm_s > 0) every policy
    runs PRE_RACE_WARM_CALLS times before the clock starts. (That it changes nothing the race
    computes, with real ONNX policies: test_the_warm_up_before_each_tick_changes_nothing_the_loop_
    computes in test_flight_core_run.py, whose warm-up arm runs it and whose baseline does not.)"""
    from cfrace.flight.loop.flight_loop import PRE_RACE_WARM_CALLS

    path = gate_path(track, 5.0, laps=1)
    results, calls = [], []
    for prewarm_s in (0.0, 0.003):
        loop = make_loop(track, {"cf1": path, "cf2": path[::-1]}, timeout_s=0.5)
        loop.prewarm_s = prewarm_s
        started = []
        start = loop.clock.start
        loop.clock.start = lambda: (started.append([d.policy.calls for d in loop.drones]), start())[1]
        res = loop.run()
        calls.append(started[0])
        results.append(([d.link.sent for d in loop.drones], [(s["laps"], s["gates_passed"]) for s in res.drones]))
    assert calls == [[0, 0], [PRE_RACE_WARM_CALLS, PRE_RACE_WARM_CALLS]]
    assert len(results[0][0][0]) > 20 and results[0] == results[1]   # every setpoint sent is the same


def test_loop_race_winner_laps_and_decimation(track):
    fast, slow = gate_path(track, 6.0, laps=2), gate_path(track, 4.0, laps=2)
    loop = make_loop(track, {"cf1": fast, "cf2": slow}, laps=2)
    res = loop.run()
    assert res.end == "finished" and res.winner == "ego"
    ego, opp = res.drones
    assert ego["laps"] == 2 and ego["gates_passed"] == 12 and len(ego["lap_times"]) == 2
    assert opp["laps"] == 1 and opp["gates_passed"] < 12
    # the lap time is the path length / speed (first lap timed from the start)
    assert ego["lap_times"][1] == pytest.approx((len(fast) - 1) / 2 * 0.01, rel=0.1)
    ticks = res.ticks
    assert loop.drones[0].policy.calls == (ticks + 1) // 2          # 50 Hz policy in a 100 Hz loop,
    assert loop.drones[1].policy.calls == ticks // 2                 # staggered by one tick
    for d in loop.drones:                                            # a setpoint every tick until the end
        assert len(d.link.sent) == ticks and d.link.stops >= 1
    assert res.safety_events == []


def test_loop_ends_in_a_draw_when_both_drones_are_stopped(track):
    from cfrace.flight.config import SafetyConfig

    # both fly out of a tight fence (the track arena + 0.3 m) at different times
    out1 = np.linspace([0.0, 5.0, 1.0], [0.0, 5.0, 3.5], 200)
    out2 = np.linspace([1.0, 5.0, 1.0], [3.5, 5.0, 1.0], 300)
    loop = make_loop(track, {"cf1": out1, "cf2": out2})
    loop.fence = type(loop.fence).from_track(track, 0.3)
    res = loop.run()
    assert res.end == "all_stopped" and res.winner == "draw"
    assert [e["kind"] for e in res.safety_events] == ["geofence", "geofence"]
    assert [e["drone"] for e in res.safety_events] == ["ego", "opp"]
    assert all(d["stopped"] and d["stop_kind"] == "geofence" for d in res.drones)
    # after its stop a drone gets no more setpoints
    assert len(loop.drones[0].link.sent) < len(loop.drones[1].link.sent)


def test_prewarm_runs_only_the_policy_due_next_tick_on_the_newest_estimates(track):
    hover = np.tile([[1.0, 2.0, 1.0]], (10, 1))
    loop = make_loop(track, {"cf1": hover, "cf2": hover + [0.5, 0, 0]}, timeout_s=0.5)
    ego, opp = loop.drones
    loop.prewarm()                             # before the first tick: zeros of each layout's size
    assert (ego.policy.calls, opp.policy.calls) == (1, 0)      # tick 0 is the ego's (phase 0)
    assert ego.policy.last.shape == (1, 42) and not ego.policy.last.any()
    loop.run()                                 # 51 ticks (k 0..50): the next one, 51, is odd
    ego.stopped = opp.stopped = False          # (the end of the race stopped both)
    n_ego, n_opp = ego.policy.calls, opp.policy.calls
    loop.prewarm()                             # next tick is odd: the opponent's policy, real observation
    assert (ego.policy.calls, opp.policy.calls) == (n_ego, n_opp + 1)
    assert opp.policy.last.shape == (1, 36) and opp.policy.last.any()
    np.testing.assert_array_equal(opp.policy.last[0], loop.obs_builder(opp.layout, loop._last_ests[1],
                                                                      int(loop.progress.target[1])))
    opp.stopped = True
    loop.prewarm()                             # a stopped drone is not warmed
    assert opp.policy.calls == n_opp + 1

    def broken(obs):
        raise RuntimeError("policy failure")
    opp.stopped, opp.policy = False, broken
    loop.prewarm()                             # never raises: the tick's own call reports it


def test_zero_thrust_from_the_policy_is_sent_as_the_firmwares_least_flying_thrust(track):
    """A policy's zero thrust (a0 = -1) goes out as FLYING_MIN_COUNTS, not 0 (which the firmware
    takes as motors off, rate control reset); a stop still sends 0 (through link.stop)."""
    from cfrace.flight.loop.flight_loop import FLYING_MIN_COUNTS

    hover = np.tile([[1.0, 2.0, 1.0]], (10, 1))
    loop = make_loop(track, {"cf1": hover, "cf2": hover + [0.5, 0, 0]}, timeout_s=0.2)

    class Dive(CountingPolicy):
        def __call__(self, obs):
            super().__call__(obs)
            return np.array([[-1.0, 1.0, 0.0, 0.0]], np.float32)
    loop.drones[0].policy = Dive(42)
    loop.run()
    sent = loop.drones[0].link.sent
    assert sent and all(c == FLYING_MIN_COUNTS for *_, c in sent)
    assert all(r == pytest.approx(100.0) for r, *_ in sent)          # full roll rate still commanded
    assert loop.drones[0].link.stops >= 1                            # the end of the race: stop (0 counts)


def test_loop_timeout(track):
    hover = np.tile([[1.0, 2.0, 1.0]], (10, 1))
    res = make_loop(track, {"cf1": hover, "cf2": hover + [0.5, 0, 0]}, timeout_s=0.5).run()
    assert res.end == "timeout" and res.winner == "draw" and res.ticks == 51


def test_real_time_loop_does_not_burst_after_a_stall(track):
    """A 35 ms stall in real time: the missed ticks are skipped, never sent late in a burst."""
    clock = RealClock(0.01)
    hover = np.tile([[1.0, 2.0, 1.0]], (10, 1))
    loop = make_loop(track, {"cf1": hover, "cf2": hover + [0.5, 0, 0]}, timeout_s=0.4, clock=clock)

    class Stall:
        fired = False

        def before_tick(self, lp, t):
            if t > 0.1 and not self.fired:
                self.fired = True
                time.sleep(0.035)

        def filter_obs(self, d, obs):
            return obs

        def filter_action(self, d, act, t):
            return act

    loop.faults = Stall()
    ticks, sends = [], []
    wait = clock.wait_next
    clock.wait_next = lambda *a: (ticks.append(wait(*a)), ticks[-1])[1]
    link = loop.drones[0].link
    orig = link.send
    link.send = lambda *a: (sends.append(ticks[-1].k), orig(*a))
    res = loop.run()
    ks = [t.k for t in ticks]
    assert ks == sorted(set(ks))                          # each deadline at most once, in order
    jump = [b - a for a, b in zip(ks, ks[1:]) if b - a > 1]
    assert jump and max(jump) >= 3                        # the stall: ticks dropped, not caught up
    assert sends == ks                                    # exactly one setpoint per executed tick
    assert all(t.t >= t.k * 0.01 for t in ticks)          # never early
    assert any(e["kind"] == "tick_skipped" for e in res.safety_events)


def test_live_view_renders_every_drone(track):
    import io

    from rich.console import Console

    from cfrace.flight.log.liveview import LiveView

    hover = np.tile([[1.0, 2.0, 1.0]], (10, 1))
    loop = make_loop(track, {"cf1": hover, "cf2": hover + [0.5, 0, 0]}, timeout_s=0.2)
    buf = io.StringIO()
    con = Console(file=buf, width=120, force_terminal=False)
    loop.view = LiveView(title="test race", laps=3, every_ticks=5, console=con)
    with loop.view:
        loop.run()
    text = buf.getvalue()
    assert "test race" in text and "ego" in text and "opp" in text and "0/3" in text
    assert "STOPPED (timeout)" in text and "t =   0.2 s" in text    # the race as it ended
    # once the race is decided the view shows it as it ended (the result's tally), not the gates a
    # drone passes while it flies on before it lands, and a landing drone as landing
    core = loop.core
    for d in core.drones:
        d.stopped, d.landing = False, object()
    core.race_over = ("finished", "ego", 0.1, [(6, 1, [3.7]), (5, 0, [])])
    core.progress.laps[:] = 3
    con.print(loop.view.render(loop, 0.3, core.last_ests))
    frame = buf.getvalue()[len(text):]
    rows = {line.split()[1]: line for line in frame.splitlines() if line.split()[1:2] in (["ego"], ["opp"])}
    assert "1/3" in rows["ego"] and "0/3" in rows["opp"] and "3/3" not in frame
    assert all("landing" in r and r.split("│")[3].strip() == "-" for r in rows.values()), frame


@pytest.mark.parametrize("profile", ["cf2x_paper", "cf21bl"])
def test_setpoint_map_is_bit_identical_to_the_training_action_map_and_the_calibration_curve(profile):
    from cfrace.drone import load_profile
    from cfrace.contract.actions import SetpointMap, action_to_command

    prof = load_profile(profile)
    m = SetpointMap(prof.mass, prof.max_thrust_weights, prof.max_rates_deg, prof.thrust_curve)
    rng = np.random.default_rng(0)
    acts = rng.uniform(-1.3, 1.3, size=(20000, 4)).astype(np.float32)
    # thrust exactly at every knot of the curve, and at the ends
    knots = np.asarray(prof.thrust_curve.newtons) / (prof.max_thrust_weights * prof.mass * 9.81) * 2.0 - 1.0
    acts[:len(knots), 0] = knots.astype(np.float32)
    acts[-4:] = [[-1, -1, -1, -1], [1, 1, 1, 1], [0, 0, 0, 0], [np.nan, 0.5, np.nan, 0.1]]
    for a in acts:
        thrust, rates, counts = m(a)
        ref_thrust, ref_rates = action_to_command(a.astype(np.float64), prof.mass, prof.max_thrust_weights,
                                                  prof.max_rates_deg)
        ref_dps = np.degrees(ref_rates)
        if not np.isfinite(ref_thrust):
            assert not math.isfinite(thrust) and counts == 0
        else:
            assert thrust == float(ref_thrust) and counts == thrust_to_counts(float(ref_thrust), prof.thrust_curve)
        np.testing.assert_array_equal(np.array(rates), ref_dps)


def test_the_race_collects_garbage_by_the_automatic_thresholds_between_ticks():
    import gc

    from cfrace.flight.loop.flight_loop import collect_garbage

    was_on = gc.isenabled()
    gc.disable()            # as during a race (cfrace.flight.loop.race._run_realtime_friendly)
    try:
        gc.collect()
        collect_garbage()   # nothing due: no collection
        assert gc.get_count()[0] < gc.get_threshold()[0]
        seen = []
        gc.callbacks.append(cb := lambda phase, info: seen.append((phase, info["generation"])))
        try:
            junk = []
            for _ in range(gc.get_threshold()[0] + 50):   # cyclic garbage past the young threshold
                a = []
                a.append(a)
                junk.append(a)
            del junk, a
            assert gc.get_count()[0] >= gc.get_threshold()[0] and seen == []   # off: nothing collected it
            collect_garbage()
        finally:
            gc.callbacks.remove(cb)
        assert seen and seen[0] == ("start", 0) and gc.get_count()[0] < gc.get_threshold()[0]
    finally:
        if was_on:
            gc.enable()
