"""Issue 15's safety holes, each through the real stack: `cfrace fly` as a process of its own,
cflib over UDP against the simulated Crazyflies (the server `cfrace sim serve` runs), real ONNX
files, the real MCAP writer. Each test failed on the main branch before the fix."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import onnx
import pytest

from cfrace.contract import decode_meta, encode_meta
from cfrace.rehearsal.hold_policy import make_hold_policy

PROFILE = "cf2x_paper"
CLI = [sys.executable, "-c", "from cfrace.cli.main import main; main()"]


@pytest.fixture(scope="module")
def pols(tmp_path_factory):
    d = tmp_path_factory.mktemp("pols")
    return {"ego": make_hold_policy(d / "ego.onnx", "race42", "lemniscate", False),
            "opp": make_hold_policy(d / "opp.onnx", "solo36", "lemniscate", False), "dir": d}


@pytest.fixture()
def served():
    """Two simulated Crazyflies served over UDP on free ports, as `cfrace sim serve` serves them."""
    from cfrace.simcf.firmware import SimFleet
    from cfrace.simcf.server import SimCrazyflieServer
    from cfrace.track import load_track

    fleet = SimFleet(load_track("lemniscate"), PROFILE, 2, body_names=["cf1", "cf2"], seed=0, obstacles=False)
    server = SimCrazyflieServer(fleet, base_port=0, pose_port=0).start()
    yield fleet, server
    server.stop()


def crafted(src: Path, dst: Path, **meta) -> Path:
    """A copy of the policy file src with metadata values replaced (written as JSON, as export does)."""
    model = onnx.load(str(src))
    values = decode_meta({p.key: p.value for p in model.metadata_props}) | meta
    del model.metadata_props[:]
    onnx.helper.set_model_props(model, encode_meta(values))
    onnx.save_model(model, str(dst))
    return dst


def fly(served, pols, tmp_path, *extra, ego=None, timeout=60) -> subprocess.CompletedProcess:
    fleet, server = served
    args = ["fly", "--track", "lemniscate", "--ego", str(ego or pols["ego"]), "--opp", str(pols["opp"]),
            "--uris", ",".join(server.uris), "--mocap", f"sim://127.0.0.1:{server.pose_port}", "--profile", PROFILE,
            "--quiet", "--log", str(tmp_path / "f.mcap"), "--timeout-s", "1", "--loop-cpu", "off", *extra]
    return subprocess.run(CLI + args, capture_output=True, text=True, timeout=timeout)


def one_clear_line(proc: subprocess.CompletedProcess, *words: str) -> str:
    err = proc.stderr.strip()
    assert proc.returncode == 2, (proc.returncode, err)
    assert "Traceback" not in err and len(err.splitlines()) == 1 and err.startswith("error: "), err
    for w in words:
        assert w in err, err
    return err


def nothing_sent(fleet) -> bool:
    """No drone was armed or given thrust (a refused race may still close its links with a zero
    setpoint and a STOP)."""
    return all(not fleet.status(i)["armed"] and fleet.status(i)["thrust_counts"] == 0
               and fleet.state(i)["pos"][2] < 0.1 for i in range(2))


# ------------------------------------------------------------------------- 2. policy metadata
@pytest.mark.parametrize("meta, word", [({"max_rates_deg": [float("inf"), 100.0, 200.0]}, "max_rates_deg"),
                                        ({"max_thrust_weights": float("nan")}, "max_thrust_weights"),
                                        ({"max_thrust_weights": 1e30}, "max_thrust_weights"),
                                        ({"policy_hz": float("nan")}, "policy_hz"),
                                        ({"max_rates_deg": [400.0, 100.0, 200.0]}, "exceeds drone profile")])
def test_unchecked_policy_metadata_is_refused_before_anything_flies(served, pols, tmp_path, meta, word):
    bad = crafted(pols["ego"], tmp_path / "bad.onnx", **meta)
    one_clear_line(fly(served, pols, tmp_path, ego=bad), str(bad), word)
    assert nothing_sent(served[0])


def test_the_safety_check_judges_the_setpoint_that_is_sent(tmp_path):
    """A drone whose action map would send rates beyond the profile's is stopped before the send."""
    from test_flight_core import gate_path, make_loop

    from cfrace.drone import load_profile
    from cfrace.contract.actions import SetpointMap
    from cfrace.flight.safety.check import CommandLimits
    from cfrace.track import load_track

    track = load_track("lemniscate")
    path = gate_path(track, 5.0)
    loop = make_loop(track, {"cf1": path, "cf2": path[::-1]}, timeout_s=0.3)
    prof = load_profile(PROFILE)
    loop.core.limits = CommandLimits.from_profile(prof)
    ego = loop.drones[0]
    ego.setpoint_map = SetpointMap(prof.mass, 3.15, [1000.0, 100.0, 200.0], prof.thrust_curve)   # 10x roll

    class Roll:
        def __call__(self, obs):
            return [[0.0, 0.5, 0.0, 0.0]]
    ego.policy = Roll()
    res = loop.run()
    assert ego.link.sent == [] and ego.stopped and ego.stop_kind == "command"
    ev = next(e for e in res.safety_events if e["kind"] == "command")
    assert ev["drone"] == "ego" and "500" in ev["detail"] and len(loop.drones[1].link.sent) > 10


# ------------------------------------------------------------------------- 6. / 8. limits
@pytest.mark.parametrize("extra, word", [(["--geofence-margin-m", "inf"], "safety.geofence_margin_m"),
                                         (["--speed-max-mps", "inf"], "safety.speed_max_mps"),
                                         (["--speed-max-mps", "1e9"], "safety.speed_max_mps"),
                                         (["--timeout-s", "nan"], "timeout_s"),
                                         (["--timeout-s", "inf"], "timeout_s")])
def test_non_finite_and_absurd_limits_are_refused_on_the_command_line(served, pols, tmp_path, extra, word):
    one_clear_line(fly(served, pols, tmp_path, *extra), word)
    assert nothing_sent(served[0])


def test_absurd_limits_are_refused_in_files_too(served, pols, tmp_path):
    import yaml

    from cfrace.paths import TRACKS_DIR

    room = tmp_path / "room.yaml"
    room.write_text("laps: 2.5\n")
    one_clear_line(fly(served, pols, tmp_path, "--config", str(room)), "laps", "whole number")
    room.write_text("safety: {speed_max_mps: 1.0e+9}\n")
    one_clear_line(fly(served, pols, tmp_path, "--config", str(room)), "speed_max_mps")
    doc = yaml.safe_load((TRACKS_DIR / "lemniscate.yaml").read_text())
    doc["arena"]["x"] = [-1e300, 1e300]
    huge = tmp_path / "huge.yaml"
    huge.write_text(yaml.safe_dump(doc))
    one_clear_line(fly(served, pols, tmp_path, "--track", str(huge)), "arena.x")
    assert nothing_sent(served[0])


def test_the_geofence_fault_leaves_the_fence_and_the_fence_stops_it(pols, tmp_path):
    """The injected fault climbs out through the fence's ceiling at a moderate speed: the stop is the
    geofence's (not the speed or tilt rule's), with the drone really outside the fence."""
    from cfrace.flight.config import FlightConfig
    from cfrace.rehearsal.dryrun import dry_run

    cfg = FlightConfig(track="lemniscate", ego=str(pols["ego"]), opp=str(pols["opp"]), profile=PROFILE, quiet=True,
                       timeout_s=4.0)
    res = dry_run(cfg, lockstep=True, faults="geofence@1.0").to_json()
    ego = [e for e in res["safety_events"] if e["drone"] == "ego" and e["action"] != "none"]
    kinds = [e["kind"] for e in ego]    # (the soft rule fence_near asks it to land first: the fault overrides)
    assert kinds[-1] == "geofence" and set(kinds) <= {"fence_near", "geofence"}, res["safety_events"]
    assert "outside the fence" in ego[-1]["detail"] and res["drones"][0]["speed_max"] < 6.0


# ------------------------------------------------------------------------- 4. logs and results at the edges
def test_output_paths_are_checked_before_take_off(served, pols, tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    one_clear_line(fly(served, pols, tmp_path, "--json", str(blocker / "r.json")), "--json", "cannot write")
    proc = fly(served, pols, tmp_path, "--log", "/dev/full")
    one_clear_line(proc, "/dev/full", "No space left")
    assert nothing_sent(served[0])


def test_signals_at_the_race_end_leave_a_complete_log_the_json_and_exit_143(served, pols, tmp_path):
    """SIGTERMs every 25 ms from just before the race's end through its stop sequence: the first
    one is the operator's kill (or follows the race), the others must not abort the stops, the
    log's close or the JSON."""
    import signal
    import time

    from cfrace.flight.log.writer import read_log

    fleet, server = served
    args = ["fly", "--track", "lemniscate", "--ego", str(pols["ego"]), "--opp", str(pols["opp"]),
            "--uris", ",".join(server.uris), "--mocap", f"sim://127.0.0.1:{server.pose_port}", "--profile", PROFILE,
            "--quiet", "--log", str(tmp_path / "f.mcap"), "--timeout-s", "2", "--loop-cpu", "off",
            "--json", str(tmp_path / "r.json")]
    proc = subprocess.Popen(CLI + args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    for line in proc.stderr:
        if "Ctrl-C stops every drone" in line:
            break
    time.sleep(1.9)                  # set-up (a fraction of a second) and most of the 2-s race
    while proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.025)
    err = proc.stderr.read()
    assert proc.returncode == 143 and "Traceback" not in err, err
    result = json.loads((tmp_path / "r.json").read_text())
    assert result["operator_kill"] == "SIGTERM"
    data = read_log(tmp_path / "f.mcap")
    assert data.complete and data.summary is not None
    assert all(fleet.status(i)["thrust"] == 0.0 for i in range(2))


# ------------------------------------------------------------------------- 3. checkpoints run no code
@pytest.mark.parametrize("command", [["export", "{ckpt}", "-o", "{tmp}/x.onnx"],
                                     ["train", "--resume", "{ckpt}", "--steps", "10"],
                                     ["train", "--method", "ds", "--track", "lemniscate", "--init-from", "{ckpt}",
                                      "--steps", "10", "--out", "{tmp}/run"]])
def test_a_crafted_checkpoint_runs_no_code_and_gets_one_line(tmp_path, command):
    import os

    import torch

    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    ckpt = tmp_path / "evil.pt"
    torch.save({"format": "cfrace-ippo-1", "runner": Evil()}, ckpt)
    args = [a.format(ckpt=ckpt, tmp=tmp_path) for a in command]
    proc = subprocess.run(CLI + args, capture_output=True, text=True, timeout=120)
    one_clear_line(proc, str(ckpt), "refused")
    assert not marker.exists()


# ------------------------------------------------------------------------- 7. crafted logs and packets
def test_a_crafted_flight_log_gets_one_line_everywhere(pols, tmp_path):
    """/mocap/pose with a list where the poses object belongs: `log plot`, `sim replay` and
    `fly --mocap replay://` say so in one line."""
    from cfrace.flight.config import FlightConfig
    from cfrace.rehearsal.dryrun import dry_run
    from cfrace.flight.log.writer import FlightLog, read_log

    real = tmp_path / "real.mcap"
    dry_run(FlightConfig(track="lemniscate", ego=str(pols["ego"]), opp=str(pols["opp"]), profile=PROFILE,
                         quiet=True, timeout_s=0.3, log=real), lockstep=True)
    data = read_log(real)
    bad = tmp_path / "crafted.mcap"
    log = FlightLog(bad, data.meta, fsync_interval_s=None)
    for topic in data.topics:
        if topic in ("/meta", "/summary"):
            continue
        for t, m in data.messages(topic):
            log.write(topic, t, {**m, "poses": [[1.0, 2.0, 3.0]]} if topic == "/mocap/pose" else m)
    log.close({})
    plot = subprocess.run(CLI + ["log", "plot", str(bad), "-o", str(tmp_path)], capture_output=True, text=True)
    assert plot.returncode == 0 and "Traceback" not in plot.stderr, plot.stderr
    one_clear_line(subprocess.run(CLI + ["sim", "replay", str(bad)], capture_output=True, text=True),
                   str(bad), "poses")
    replay = subprocess.run(CLI + ["fly", "--track", "lemniscate", "--ego", str(pols["ego"]), "--opp", str(pols["opp"]),
                                   "--uris", "null://a,null://b", "--mocap", f"replay://{bad}", "--profile", PROFILE,
                                   "--quiet", "--log", str(tmp_path / "f.mcap")], capture_output=True, text=True)
    one_clear_line(replay, str(bad), "poses")


def test_sim_serve_reports_bad_packets_in_one_rate_limited_line(tmp_path):
    """Over-long datagrams on the echo and platform channels: no traceback, one line a second."""
    import os
    import socket
    import time

    from cfrace.rehearsal.loop_timing import _free_base_port

    base = _free_base_port()
    proc = subprocess.Popen(CLI + ["sim", "serve", "--track", "lemniscate", "--port", str(base), "--profile", PROFILE],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        for line in proc.stdout:
            if "Ctrl-C" in line:
                break
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for k in range(200):
                s.sendto(bytes([0xF0 if k % 2 else 0xDC, 0]) + b"x" * 100, ("127.0.0.1", base))
            time.sleep(0.5)
    finally:
        proc.terminate()
        try:
            _, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 2, err
    assert "bad packet" in err


# ------------------------------------------------------------------------- 1. flying blind
def test_recorded_or_foreign_poses_do_not_steer_live_drones(served, pols, tmp_path):
    """replay:// poses with live links are refused before anything flies; a moving replay is
    caught by the before-take-off check (the poses must stay still while nothing is armed)."""
    from cfrace.flight.config import FlightConfig
    from cfrace.flight.mocap.consistency import check_still
    from cfrace.rehearsal.dryrun import dry_run
    from cfrace.flight.mocap.sources import open_mocap

    log = tmp_path / "recorded.mcap"
    dry_run(FlightConfig(track="lemniscate", ego=str(pols["ego"]), opp=str(pols["opp"]), profile=PROFILE,
                         quiet=True, timeout_s=1.5, log=log), lockstep=True)
    one_clear_line(fly(served, pols, tmp_path, "--mocap", f"replay://{log}"), "recorded poses", "null://")
    assert nothing_sent(served[0])
    source = open_mocap(f"replay://{log}?speed=2", bodies=["cf1", "cf2"])
    source.open()
    with pytest.raises(Exception, match=r"mocap body cf\d moved .* before take-off"):
        check_still(source, ["cf1", "cf2"], 1.0)
    source.close()


def test_swapped_mocap_bodies_are_stopped_once_the_drones_fly(served, pols, tmp_path):
    """`fly --bodies cf2,cf1` against the served drones: each drone is steered on the other's poses.
    A ground start sees it first: each body stands on the other drone's start slot, refused with
    nothing sent. With that check off (safety.start_slot_m: 0) the drones take off to different
    heights, the poses stop moving with the commands and every drone is stopped (pose_mismatch)
    within 0.3 s of leaving the floor."""
    from cfrace.rehearsal.hold_policy import make_hold_policy

    high = make_hold_policy(tmp_path / "high.onnx", "solo36", "lemniscate", False, height_offset=0.6)
    one_clear_line(fly(served, {**pols, "opp": high}, tmp_path, "--bodies", "cf2,cf1"),
                   "not on the start grid", "cf2 stands at (1.70, 2.50)", "0.40 m from its slot (1.30, 2.50)")
    assert nothing_sent(served[0])
    room = tmp_path / "room.yaml"
    room.write_text("safety:\n  start_slot_m: 0\n")
    proc = fly(served, {**pols, "opp": high}, tmp_path, "--bodies", "cf2,cf1", "--timeout-s", "4",
               "--json", str(tmp_path / "r.json"), "--config", str(room))
    result = json.loads((tmp_path / "r.json").read_text())
    assert result["end"] == "pose_mismatch", (result["end"], result["safety_events"], proc.stderr[-500:])
    ev = next(e for e in result["safety_events"] if e["kind"] == "pose_mismatch")
    assert ev["t"] < 1.5 and all(d["stopped"] for d in result["drones"])


# ------------------------------------------------------------------------- the fault suite
def test_fault_suite_rows_pass_and_catch_a_replay(tmp_path):
    """Two rows of `cfrace sim faults` (the whole suite runs for minutes): a replay of the frames of
    1 s earlier mid-race is stopped by the consistency check within 0.3 s, with a complete log."""
    from cfrace.rehearsal.fault_suite import FAULT_T, dry_run_row, markdown

    row = dry_run_row("replay_poses", "lemniscate", tmp_path)
    assert row.passed and row.log_complete and row.exit_code == 3, row   # every drone stopped: exit 3
    assert FAULT_T <= row.detected_s <= FAULT_T + 0.3 and row.stopped_s <= FAULT_T + 0.3
    table = markdown([row])
    assert table.count("\n") == 2 and "| fault replay_poses@2 (ego) |" in table and "| pass |" in table


def test_fault_suite_knows_every_fault_and_times_a_landing(tmp_path):
    """Every fault kind has its expected detection in the suite (a kind without one ended
    `cfrace sim faults` with a KeyError); a soft failsafe's row says when its landing touched down."""
    from cfrace.rehearsal.faults import KINDS
    from cfrace.rehearsal.fault_suite import EXPECT, FAULT_T, dry_run_row

    assert set(EXPECT) == set(KINDS)
    row = dry_run_row("low_battery", "lemniscate", tmp_path)
    assert row.passed and row.exit_code == 0, row
    assert FAULT_T < row.detected_s < row.stopped_s and row.distance_m < 5.0, row
