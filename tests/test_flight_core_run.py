"""Whole-stack runs: `cfrace sim dry-run` (lockstep and real time through cflib), replay, and bad
input that must be refused with one line before anything is sent to a drone."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cfrace.errors import CfraceError, MocapError, PolicyError
from cfrace.flight.config import FlightConfig, SafetyConfig
from cfrace.rehearsal.dryrun import dry_run
from cfrace.flight.log.writer import read_log
from cfrace.rehearsal.replay import replay_log
from cfrace.rehearsal.hold_policy import make_hold_policy

PROFILE = "cf2x_paper"


@pytest.fixture(scope="module")
def pols(tmp_path_factory):
    d = tmp_path_factory.mktemp("pols")
    return {"ego": str(make_hold_policy(d / "ego.onnx", "race42", "lemniscate", False)),
            "opp": str(make_hold_policy(d / "opp.onnx", "solo36", "lemniscate", False)),
            "complex": str(make_hold_policy(d / "cx.onnx", "race42", "complex", False)),
            "dir": d}


def cfg(pols, tmp_path, **kw):
    base = dict(track="lemniscate", ego=pols["ego"], opp=pols["opp"], profile=PROFILE, quiet=True,
                timeout_s=3.0, log=tmp_path / "flight.mcap")
    base.update(kw)
    return FlightConfig(**base)


def check_stopped_and_logged(result, log_path):
    for d in result["drones_final"]:
        assert d["motors_off"] and d["thrust_n"] == 0.0, d
    data = read_log(log_path)
    assert data.complete and data.summary is not None and data.summary["end"] == result["end"]
    return data


@pytest.fixture(scope="module")
def lockstep_run(pols, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("lockstep")
    from dataclasses import replace

    # a non-default velocity filter and latency compensation: the replay must take them from the log
    # to reproduce the observations
    result = dry_run(replace(cfg(pols, tmp), velocity_alpha=0.7, latency_comp_s=0.008), lockstep=True).to_json()
    return result, tmp / "flight.mcap"


def test_lockstep_dry_run_flies_and_logs(lockstep_run):
    result, log = lockstep_run
    assert result["end"] == "timeout" and result["winner"] == "draw" and result["safety_events"] == []
    data = check_stopped_and_logged(result, log)
    assert data.meta["velocity_alpha"] == 0.7 and data.meta["latency_prediction"] == "commanded_always"
    for topic in ("/mocap/pose", "/estimate", "/obs", "/action", "/setpoint", "/timing", "/link", "/race"):
        assert data.count(topic) > 0, topic
    assert data.count("/obs") == 301                                           # 100 Hz loop, 3 s race
    landing_ticks = data.count("/timing") - 301                                # then both drones land
    assert 0 < landing_ticks < 500 and {m["drone"] for _, m in data.messages("/landing")} == {"ego", "opp"}
    obs = [m for _, m in data.messages("/obs")]                                # 50 Hz each, staggered
    assert [m["k"] for m in obs if "cf1" in m] == list(range(0, 301, 2))
    assert [m["k"] for m in obs if "cf2" in m] == list(range(1, 301, 2))
    z = [m["cf1"]["pos"][2] for _, m in data.messages("/estimate")]
    assert z[0] < 0.05 and max(z) > 0.6                                        # took off from the floor
    assert result["loop"]["ticks"] == 301 + landing_ticks and result["loop"]["skipped"] == 0
    assert data.meta["policies"]["ego"]["obs_layout"] == "race42"


def test_replay_reproduces_the_observations_exactly(lockstep_run):
    _, log = lockstep_run
    r = replay_log(log)
    assert r["identical"] and r["observations"] == 151 + 150 and r["mismatched"] == 0
    r = replay_log(log, via_replay_source=True)     # the same through the mocap source replay://LOG?speed=0
    assert r["identical"] and r["observations"] == 151 + 150


def test_replay_of_a_cut_log_ends_at_its_last_tick(lockstep_run, tmp_path):
    """A log cut mid-flight (a killed process): the race's timeout in /meta lies beyond its last tick,
    and the replay, which lands drones as the flight did, still ends there and matches what was logged."""
    _, log = lockstep_run
    cut = tmp_path / "cut.mcap"
    data = log.read_bytes()
    cut.write_bytes(data[:len(data) // 2])
    assert read_log(cut).meta["timeout_s"] > 1.0 and read_log(cut).meta["landing"]
    r = replay_log(cut)
    assert r["identical"] and 0 < r["observations"] < 151 + 150 and r["not_replayed"] == 0


def test_replay_detects_a_different_flight(lockstep_run, tmp_path):
    """The check can fail: replaying with frames of another flight does not match."""
    import shutil

    from cfrace.rehearsal import replay as rp

    _, log = lockstep_run
    copy = tmp_path / "copy.mcap"
    shutil.copy(log, copy)
    orig = rp.frame_from_msg

    def shifted(msg):
        f = orig(msg)
        for p in f.poses.values():
            p.pos[0] += 0.01
        return f
    rp.frame_from_msg = shifted
    try:
        r = replay_log(copy)
    finally:
        rp.frame_from_msg = orig
    assert not r["identical"] and r["mismatched"] > 100


def test_replay_flies_the_logs_prediction_rule(lockstep_run, monkeypatch):
    """A replay predicts as its log's latency_prediction says: the same log replayed with the rule of
    older logs ("velocity") no longer matches, and a rule the estimator does not know is one
    LogError line, not a traceback."""
    from cfrace.errors import LogError
    from cfrace.rehearsal import replay as rp

    _, log = lockstep_run
    real = rp.read_log

    def with_rule(rule):
        def read(path):
            data = real(path)
            data.meta["latency_prediction"] = rule
            return data
        return read
    monkeypatch.setattr(rp, "read_log", with_rule("velocity"))
    r = replay_log(log)
    assert not r["identical"] and r["mismatched"] > 0
    monkeypatch.setattr(rp, "read_log", with_rule("telepathy"))
    with pytest.raises(LogError, match="latency_prediction 'telepathy'"):
        replay_log(log)


def test_real_time_dry_run_through_cflib(pols, tmp_path):
    import gc

    assert gc.isenabled()
    result = dry_run(cfg(pols, tmp_path, timeout_s=2.0), lockstep=False).to_json()
    assert gc.isenabled()   # the race turned the automatic collection off (the loop collects) and back on
    assert result["end"] == "timeout", ([(e["t"], e["kind"], e["detail"]) for e in result["safety_events"]],
                                        result.get("landings"))
    # the defaults: SCHED_FIFO where this process may, the loop thread on a CPU of its own
    from test_flight_realtime import fifo_permitted
    from cfrace.flight.loop.realtime import resolve_loop_cpu
    assert result["rt_fifo"] == fifo_permitted() and result["loop_cpu"] == resolve_loop_cpu("auto")
    # on a loaded machine a tick can be skipped (reported, action none); nothing may stop a drone
    assert all(e["action"] == "none" for e in result["safety_events"]), result["safety_events"]
    data = check_stopped_and_logged(result, tmp_path / "flight.mcap")
    loop = result["loop"]
    assert loop["ticks"] + loop["skipped"] >= 195 and loop["compute_p99_ms"] > 0
    assert data.meta["uris"][0].startswith("udp://127.0.0.1:")
    links = [m for _, m in data.messages("/link")]
    assert links[-1]["cf1"]["connected"] and links[-1]["cf1"]["sent"] > 150
    assert any(m["cf1"]["latency_ms"] is not None for m in links)          # cflib echo pings answered
    z = [m["cf2"]["pos"][2] for _, m in data.messages("/estimate")]
    assert max(z) > 0.5
    # a real-time log replays exactly too: frames by tick, loop-clock times from /timing
    r = replay_log(tmp_path / "flight.mcap")
    assert r["identical"] and r["observations"] > 150


# ------------------------------------------------------------------------------- refused before flying

def _fleet_and_race(pols, tmp_path, **kw):
    from cfrace.rehearsal.dryrun import sim_race
    from cfrace.flight.setup import resolve_race
    from cfrace.simcf.firmware import SimFleet

    c = cfg(pols, tmp_path, **kw)
    fleet = SimFleet("lemniscate", PROFILE, 2, obstacles=False)
    try:
        sim_race(resolve_race(c), fleet).to_json()
    finally:
        for i in range(2):
            assert fleet.status(i)["setpoints_received"] == 0         # nothing was sent
            assert fleet.get_param(i, "flightmode.stabModeRoll") == 1   # not even the set-up


def test_mismatched_policy_is_refused_before_anything_flies(pols, tmp_path):
    with pytest.raises(PolicyError, match="trained on track 'complex', not 'lemniscate'"):
        _fleet_and_race(pols, tmp_path, ego=pols["complex"])
    with pytest.raises(PolicyError, match="without obstacles, but the race is with"):
        _fleet_and_race(pols, tmp_path, obstacles=True)


def test_a_link_type_without_the_whole_link_protocol_is_refused_before_anything_is_sent(pols, tmp_path):
    """A new link type (docs/architecture.md, "How to add ...") that lacks part of the Link protocol
    is refused with one line naming what it lacks, before any link connects, not mid-race."""
    from dataclasses import replace

    from cfrace.errors import LinkError
    from cfrace.rehearsal.dryrun import sim_io
    from cfrace.flight.loop.race import run_race
    from cfrace.flight.setup import resolve_race
    from cfrace.simcf.firmware import SimFleet

    class HalfLink:                       # connect, setup, send, stop, close, quality: not enough
        def __init__(self, uri):
            self.uri = uri

        def connect(self, timeout_s):
            raise AssertionError("connected")

        setup = send = stop = close = connect
        quality = None

    c = cfg(pols, tmp_path)
    fleet = SimFleet("lemniscate", PROFILE, 2, obstacles=False)
    io = sim_io(c, fleet, lockstep=True, uris=["sim://0", "sim://1"])
    made = io.open_link
    io = replace(io, open_link=lambda i, uri: made(i, uri) if i == 0 else HalfLink(uri))
    with pytest.raises(LinkError, match=r"sim://1: HalfLink is not a cfrace Link: it lacks high_level, notify_stop, "
                                        r"read_status, send_pose \(the Link protocol"):
        run_race(resolve_race(c), io)
    assert fleet.status(0)["setpoints_received"] == 0 and fleet.get_param(0, "flightmode.stabModeRoll") == 1


def test_corrupt_policy_is_refused(pols, tmp_path):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"\x08\x07garbage" * 10)
    with pytest.raises(PolicyError, match="not a valid ONNX model"):
        _fleet_and_race(pols, tmp_path, opp=str(bad))


def test_unknown_body_is_refused(pols, tmp_path):
    with pytest.raises(MocapError, match="unknown mocap body 'cf9'"):
        _fleet_and_race(pols, tmp_path, bodies=("cf1", "cf9"), mocap_timeout_s=0.3)


def run_cli(args, monkeypatch, capsys):
    """The real entry point in-process: returns (exit code, stdout, stderr)."""
    from cfrace.cli.main import main

    monkeypatch.setattr(sys, "argv", ["cfrace", *args])
    with pytest.raises(SystemExit) as e:
        main()
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


@pytest.fixture()
def server():
    from cfrace.simcf.firmware import SimFleet
    from cfrace.simcf.server import SimCrazyflieServer

    s = SimCrazyflieServer(SimFleet("lemniscate", PROFILE, 2, obstacles=False), base_port=0).start()
    yield s
    s.stop()


def _free_port():
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("case", ["unknown_body", "mismatched_onnx", "corrupt_onnx", "malformed_replay",
                                  "truncated_replay", "radio_without_crazyradio", "udp_nothing_listening",
                                  "loop_cpu_missing", "rt_priority_bad"])
def test_fly_refuses_bad_input_with_one_line(case, pols, lockstep_run, server, tmp_path, monkeypatch, capsys):
    _, log = lockstep_run
    args = dict(track="lemniscate", ego=pols["ego"], opp=pols["opp"], uris=",".join(server.uris),
                mocap=f"sim://127.0.0.1:{server.pose_port}", profile=PROFILE, log=str(tmp_path / "f.mcap"),
                bodies="cf1,cf2")
    expect = {"unknown_body": "unknown mocap body 'cf9'", "mismatched_onnx": "trained on track 'complex'",
              "corrupt_onnx": "not a valid ONNX model", "malformed_replay": "not an MCAP flight log",
              "truncated_replay": "replay://", "radio_without_crazyradio": "recorded poses belong to the recorded drones",
              "udp_nothing_listening": "nothing listens there",
              "loop_cpu_missing": "loop_cpu: CPU 4095 is not available to this process",
              "rt_priority_bad": "rt_priority: must be in [0, 99], got 120"}[case]
    if case == "unknown_body":
        args["bodies"] = "cf1,cf9"
    elif case == "mismatched_onnx":
        args["opp"] = pols["complex"]
    elif case == "corrupt_onnx":
        (tmp_path / "x.onnx").write_bytes(b"not onnx at all")
        args["ego"] = str(tmp_path / "x.onnx")
    elif case == "malformed_replay":
        (tmp_path / "bad.mcap").write_bytes(b"hello, this is not mcap" * 5)
        args["mocap"] = f"replay://{tmp_path / 'bad.mcap'}"
        args["uris"] = "null://ego,null://opp"     # recorded poses fly no live link
    elif case == "truncated_replay":
        (tmp_path / "cut.mcap").write_bytes(log.read_bytes()[:40])
        args["mocap"] = f"replay://{tmp_path / 'cut.mcap'}"
        args["uris"] = "null://ego,null://opp"
    elif case == "radio_without_crazyradio":
        args["uris"] = "radio://0/80/2M/E7E7E7E7E7,radio://0/80/2M/E7E7E7E7E8"
        args["mocap"] = f"replay://{log}?speed=0"  # refused before the radio: recorded poses, live links
    elif case == "udp_nothing_listening":
        args["uris"] = f"udp://127.0.0.1:{_free_port()},{server.uris[1]}"
    elif case == "loop_cpu_missing":
        if not hasattr(os, "sched_setaffinity"):
            pytest.skip("no CPU affinity on this OS: --loop-cpu pins nothing there")
        args["loop-cpu"] = "4095"
    elif case == "rt_priority_bad":
        args["rt-priority"] = "120"
    argv = ["fly", "--quiet"] + [x for k, v in args.items() for x in (f"--{k}", v)]
    code, out, err = run_cli(argv, monkeypatch, capsys)
    assert code == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and expect in lines[0], err
    assert "Traceback" not in err
    for s in server.stats():               # nothing was sent to the simulated drones that do exist
        assert s["setpoints"] == 0, s
    if case not in ("udp_nothing_listening", "unknown_body"):   # (the sim:// pose stream needs no link)
        assert all(server.fleet.status(i)["packets_received"] == 0 for i in range(2))


def test_fly_cli_subprocess_unreachable_uri(pols, server):
    """The installed command, a real process: one line, exit code 2 (the poses of simulated drones,
    links to where no drone is)."""
    p1, p2 = _free_port(), _free_port()
    r = subprocess.run([sys.executable, "-c", "from cfrace.cli.main import main; main()", "fly", "--track", "lemniscate", "--ego", pols["ego"],
                        "--opp", pols["opp"], "--uris", f"udp://127.0.0.1:{p1},udp://127.0.0.1:{p2}",
                        "--mocap", f"sim://127.0.0.1:{server.pose_port}", "--profile", PROFILE, "--quiet",
                        "--log", str(pols["dir"] / "x.mcap")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines() == [f"error: udp://127.0.0.1:{p1}: nothing listens there (connection refused)"]


def test_the_flight_stack_flies_a_policy_like_the_training_simulator(tmp_path):
    """No train/deploy skew end to end: the same policy from the same start, once in the training
    simulator (50 Hz, build_observations on the true state, action map, 10 substeps) and once
    through the flight stack in lockstep (sim mocap -> estimator -> observation -> ONNX -> rate
    and thrust-count conversion -> DirectSimLink -> simulated firmware): the trajectories agree
    within centimetres while the drone climbs, turns to and flies through gate 0."""
    import math

    import torch

    from cfrace.drone import load_profile
    from cfrace.contract.actions import action_to_command
    from cfrace.contract.observations import LAYOUTS, build_observations
    from cfrace.rehearsal.dryrun import sim_race
    from cfrace.flight.setup import resolve_race
    from cfrace.policy import OnnxPolicy
    from cfrace.sim.simulator import Simulator
    from cfrace.simcf.firmware import SimFleet
    from cfrace.track import load_track

    track, prof = load_track("lemniscate"), load_profile(PROFILE)
    paths = [make_hold_policy(tmp_path / "a.onnx", "solo36", "lemniscate", False, seek=3.0),
             make_hold_policy(tmp_path / "b.onnx", "solo36", "lemniscate", False)]
    start = np.array([[1.3, 2.2, 0.5], [-1.5, 2.5, 0.6]])
    fleet = SimFleet(track, prof, 2, start_positions=start, obstacles=False)
    c = FlightConfig(track="lemniscate", ego=str(paths[0]), opp=str(paths[1]), profile=PROFILE, quiet=True,
                     timeout_s=2.0, log=tmp_path / "f.mcap", safety=SafetyConfig(start_slot_m=0.0))   # in the air
    sim_race(resolve_race(c), fleet).to_json()
    flown = {round(t, 4): np.array(m["poses"]["cf1"]["pos"]) for t, m in read_log(tmp_path / "f.mcap").messages("/mocap/pose")}

    sim = Simulator(track, prof, worlds=1, drones=2, obstacles=False)
    yaw = fleet._start_yaw
    q = torch.tensor([[[math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)]] * 2], dtype=torch.float32)
    sim.reset(torch.tensor([0]), torch.tensor(start[None], dtype=torch.float32), quat=q)
    pols = [OnnxPolicy(p) for p in paths]
    corners = torch.as_tensor(track.gate_corners(), dtype=torch.float32)
    trained = {}
    for k in range(100):
        trained[round(k * 0.02, 4)] = sim.pos[0, 0].double().numpy().copy()
        obs = build_observations(sim.pos[0], sim.vel[0], sim.rot()[0], sim.target[0], corners, LAYOUTS["solo36"]).numpy()
        act = torch.as_tensor(np.stack([pols[i](obs[i][None])[0] for i in range(2)]))
        thrust, rates = action_to_command(act, prof.mass, prof.max_thrust_weights, prof.max_rates_deg)
        sim.step(thrust[None].float(), rates[None].float(), substeps=10)
    dist = {t: float(np.linalg.norm(trained[t] - flown[t])) for t in (0.5, 1.0, 1.9)}
    assert float(np.linalg.norm(trained[1.9] - trained[0.0])) > 2.0    # it really flew somewhere
    assert dist[0.5] < 0.01 and dist[1.0] < 0.03 and dist[1.9] < 0.1, dist


@pytest.mark.parametrize("policy", ["ours", "ds"])
def test_shipped_policy_races_alone_through_the_flight_stack(policy, tmp_path):
    """The whole stack in lockstep (estimator, observation, ONNX, action map, thrust counts, the
    simulated firmware) flies a shipped policy two laps from the floor, the other drone stopped by
    the safety check at once. Each of the firmware's zero-thrust rule, the thrust curve ending at
    the motors' saturation and the old velocity filter made every shipped policy crash in lap 1."""
    from cfrace.rehearsal.dryrun import dry_run

    c = FlightConfig(track="lemniscate", ego=policy, opp="ds", profile=PROFILE, quiet=True, laps=2, timeout_s=20.0,
                     log=tmp_path / "alone.mcap")
    r = dry_run(c, lockstep=True, faults="nan_policy@0.02:opp", mocap_noise_m=0.0005).to_json()
    ego, opp = r["drones"]
    assert r["winner"] == "ego" and r["end"] == "finished", (ego, opp)
    assert ego["laps"] == 2 and ego["gates_passed"] == 12
    assert all(3.0 < lap < 6.0 for lap in ego["lap_times"])
    assert opp["stop_kind"] == "non_finite" and opp["gates_passed"] == 0


def test_the_simulated_crazyflie_flies_the_training_simulators_model(tmp_path):
    """The policy's commands in a lockstep dry-run (thrust in newtons as the action map gives it,
    floored at the firmware's least flying thrust; body rates), replayed open loop in the training
    simulator, give the trajectory the simulated Crazyflie flew after thrust counts, the profile's
    curve and the firmware's rules. With the thrust curve ending at the motors' saturation (0.575 N,
    as until 2026-11-22) the link clipped the commands and the two parted by centimetres within 1 s."""
    import torch

    from cfrace.drone import load_profile
    from cfrace.rehearsal.dryrun import dry_run
    from cfrace.flight.log.writer import read_log
    from cfrace.contract.actions import FIRMWARE_MIN_THRUST_COUNTS
    from cfrace.sim.simulator import CrashRules, Simulator
    from cfrace.track import load_track

    log = tmp_path / "ds.mcap"
    c = FlightConfig(track="lemniscate", ego="ds", opp="ds", profile=PROFILE, quiet=True, laps=1, timeout_s=3.0, log=log)
    dry_run(c, lockstep=True, faults="nan_policy@0.02:opp").to_json()
    data = read_log(log)
    poses = {m["seq"]: m["poses"]["cf1"] for _, m in data.messages("/mocap/pose")}
    setpoints = [(round(t / 0.01), m["cf1"]) for t, m in data.messages("/setpoint")]
    prof = load_profile(PROFILE)
    sim = Simulator(load_track("lemniscate"), prof, 1, 1, obstacles=False, rules=CrashRules(floor_grace_s=None, arena=False))
    k0 = setpoints[0][0]
    first = poses[min(poses)]
    sim.reset(torch.arange(1), torch.tensor(first["pos"]).view(1, 1, 3), quat=torch.tensor(first["quat"]).view(1, 1, 4))
    floor = float(prof.thrust_curve.to_newtons(FIRMWARE_MIN_THRUST_COUNTS))
    errors = []
    for k, sp in setpoints[:250]:
        newtons = 0.0 if sp["stopped"] or sp["thrust_counts"] == 0 else max(float(sp["thrust_n"]), floor)
        rates = torch.tensor(np.radians(sp["rates_dps"]), dtype=torch.float32).view(1, 1, 3)
        sim.step(torch.tensor([[newtons]]), rates, substeps=5)
        flown = poses.get(k + 1 - k0 + min(poses))
        if flown is not None:
            errors.append(float(np.linalg.norm(sim.state.pos[0, 0].numpy() - np.asarray(flown["pos"]))))
    race_end = min(poses) + 300                        # the race's last frame (then it lands)
    path = float(np.linalg.norm(np.asarray(poses[race_end]["pos"]) - np.asarray(first["pos"])))
    assert len(errors) > 200 and path > 3.0            # it flew, through the fast part after gate 2
    assert max(errors) < 0.005, max(errors)            # 5 mm over 2.5 s of flight


def test_the_warm_up_before_each_tick_changes_nothing_the_loop_computes(tmp_path):
    """The real-time loop runs, just before every tick, the tick's pure parts on the newest data
    (estimator and race progress on copies of their state, observation, ONNX, action map, safety
    check; FlightLoop.prewarm). Run three times before every tick in lockstep, the race (ours
    against ds with pose noise, a pose outlier and a short mocap dropout for the estimator's
    state machine) must be the same to the last bit: estimates, observations, actions,
    setpoints, gate passes, safety events and counters."""
    def race(warm_calls: int, name: str):
        c = FlightConfig(track="lemniscate", ego="ours", opp="ds", profile=PROFILE, quiet=True, laps=1,
                         timeout_s=2.5, log=tmp_path / name)
        r = dry_run(c, lockstep=True, faults="pose_outlier@0.6,mocap_dropout_short@1.2:opp",
                    mocap_noise_m=0.002, lockstep_warm_calls=warm_calls).to_json()
        return r, read_log(tmp_path / name)

    (plain, plain_log), (warm, warm_log) = race(0, "plain.mcap"), race(3, "warm.mcap")
    assert plain_log.summary["loop"]["prewarm_calls_mean"] == 0.0
    assert warm_log.summary["loop"]["prewarm_calls_mean"] == pytest.approx(3.0, abs=0.01)
    topics = ("/estimate", "/obs", "/action", "/setpoint", "/race", "/safety")
    for topic in topics:
        a, b = list(plain_log.messages(topic)), list(warm_log.messages(topic))
        assert len(a) == len(b) and len(a) > 0 or topic in ("/race",), topic
        for (ta, ma), (tb, mb) in zip(a, b):
            assert ta == tb
            np.testing.assert_equal(ma, mb, err_msg=topic)
    assert sum(1 for _ in plain_log.messages("/obs")) > 100
    assert [e["kind"] for e in plain["safety_events"]] == [e["kind"] for e in warm["safety_events"]]
    assert "pose_outlier" in [e["kind"] for e in plain["safety_events"]]
    assert plain["drones"] == warm["drones"] and plain["estimator"] == warm["estimator"]


def test_mocap_latency_compensation_keeps_a_trained_policy_flying_at_40_ms(tmp_path):
    """The ours of 2026-12-02 (tests/data; the shipped one since flies to 20 ms, docs/flight.md) alone
    through the lockstep stack with every pose 40 ms late: without compensation it falls in lap 1 (it
    flies with up to 30 ms); with the estimator predicting each pose 40 ms ahead (position with the
    velocity, attitude with the body rates; `latency_comp_s`) it flies two laps."""
    from dataclasses import replace

    ours = str(Path(__file__).parent / "data" / "ours_lemniscate_stage5.onnx")
    base = FlightConfig(track="lemniscate", ego=ours, opp="ds", profile=PROFILE, quiet=True, laps=2, timeout_s=15.0)
    late = dry_run(replace(base, latency_comp_s=0.0), lockstep=True, faults="nan_policy@0.02:opp",
                   mocap_latency_s=0.040).to_json()
    ego = late["drones"][0]
    assert ego["stopped"] and ego["laps"] == 0 and ego["stop_kind"] != "finished", ego
    comp = dry_run(replace(base, log=tmp_path / "comp.mcap"), lockstep=True, faults="nan_policy@0.02:opp",
                   mocap_latency_s=0.040).to_json()       # latency_comp_s None: the dry-run makes up for its latency
    assert comp["winner"] == "ego" and comp["drones"][0]["laps"] == 2, comp["drones"][0]
    assert read_log(tmp_path / "comp.mcap").meta["latency_comp_s"] == 0.040


def test_latency_options_reach_the_flight_and_its_log(pols, tmp_path, monkeypatch, capsys):
    """`cfrace sim dry-run --mocap-latency-ms` simulates the latency and, unless told otherwise,
    makes up for it; `--latency-comp-ms` overrides; `cfrace fly` refuses an out-of-range value
    with one line before anything is opened."""
    log = tmp_path / "lat.mcap"
    argv = ["sim", "dry-run", "--lockstep", "--track", "lemniscate", "--ego", pols["ego"], "--opp", pols["opp"],
            "--profile", PROFILE, "--laps", "1", "--timeout-s", "1", "--log", str(log), "--mocap-latency-ms", "25"]
    code, out, err = run_cli(argv, monkeypatch, capsys)
    assert code in (0, None), err   # a timeout draw is a normal end
    data = read_log(log)
    assert data.meta["mocap_latency_s"] == 0.025 and data.meta["latency_comp_s"] == 0.025

    def ages(data):   # loop clock at the tick minus the simulator's time of the pose it used
        timing = {m["k"]: m["now"] for _, m in data.messages("/timing")}
        return [timing[m["k"]] - m["t_src"] for _, m in data.messages("/mocap/pose") if m["k"] in timing][5:]

    age25 = ages(data)
    code, out, err = run_cli(argv[:-1] + ["5", "--latency-comp-ms", "0"], monkeypatch, capsys)
    data = read_log(log)
    assert data.meta["latency_comp_s"] == 0.0 and data.meta["mocap_latency_s"] == 0.005
    age5 = ages(data)
    assert len(age25) > 50 and max(age25) - min(age25) < 1e-6 and max(age5) - min(age5) < 1e-6
    assert age25[0] - age5[0] == pytest.approx(0.020, abs=1e-6)   # the poses are 20 ms older
    code, out, err = run_cli(["fly", "--track", "lemniscate", "--ego", pols["ego"], "--opp", pols["opp"],
                              "--uris", "udp://127.0.0.1:1,udp://127.0.0.1:2", "--mocap", "vicon://10.0.0.1",
                              "--latency-comp-ms", "150", "--quiet", "--log", str(tmp_path / "x.mcap")],
                             monkeypatch, capsys)
    assert code == 2 and err.strip().splitlines() == [
        "error: latency_comp_s: must be in [0, 0.1) s, got 0.15"], err


def test_profile_trained_names_the_profile_it_cannot_find(tmp_path):
    """--profile trained: a policy trained on a profile file outside calibration/ (or on another file
    of a shipped profile's name) is refused with one line, not flown on the default profile."""
    from cfrace.cli.common import choose_profile
    from cfrace.rehearsal.hold_policy import make_hold_policy
    from cfrace.paths import CALIBRATION_DIR
    from cfrace.track import load_track

    text = (CALIBRATION_DIR / "cf2x_paper.yaml").read_text()
    (tmp_path / "mine.yaml").write_text(text.replace("name: cf2x_paper", "name: mine"))
    (tmp_path / "other.yaml").write_text(text.replace("max_rates_deg: [100.0, 100.0, 200.0]", "max_rates_deg: [120.0, 120.0, 200.0]"))
    track = load_track("lemniscate")
    assert choose_profile("trained", track, str(make_hold_policy(tmp_path / "a.onnx", "solo36", "lemniscate", False)),
                          False)[0] == "cf2x_paper"
    for prof, says in (("mine.yaml", "not in"), ("other.yaml", "other than")):
        pol = make_hold_policy(tmp_path / f"{prof}.onnx", "solo36", "lemniscate", False, profile=str(tmp_path / prof))
        with pytest.raises(CfraceError, match=says):
            choose_profile("trained", track, str(pol), False)
