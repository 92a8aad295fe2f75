"""Faults through the real stack in simulation: each ends with every simulated drone stopped
(firmware status: motors off), a complete flight log with /summary and the safety event logged."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from cfrace.errors import ConfigError
from cfrace.flight.config import FlightConfig
from cfrace.rehearsal.dryrun import dry_run
from cfrace.rehearsal.faults import parse_faults
from cfrace.flight.log.writer import read_log
from cfrace.rehearsal.hold_policy import make_hold_policy

PROFILE = "cf2x_paper"


@pytest.fixture(scope="module")
def pols(tmp_path_factory):
    d = tmp_path_factory.mktemp("pols")
    return {"ego": str(make_hold_policy(d / "ego.onnx", "race42", "lemniscate", False)),
            "opp": str(make_hold_policy(d / "opp.onnx", "solo36", "lemniscate", False))}


def checked_dry_run(cfg: FlightConfig, faults, lockstep: bool):
    """dry_run; every simulated drone ends with its motors off and the log is complete."""
    result = dry_run(cfg, lockstep=lockstep, faults=faults).to_json()
    for d in result["drones_final"]:
        assert d["motors_off"] and d["thrust_n"] == 0.0, d
    data = read_log(cfg.log)
    assert data.complete and data.summary["end"] == result["end"]
    return result, data


def run(pols, tmp_path, faults, *, lockstep=True, timeout_s=3.0):
    cfg = FlightConfig(track="lemniscate", ego=pols["ego"], opp=pols["opp"], profile=PROFILE, quiet=True,
                       timeout_s=timeout_s, log=tmp_path / "f.mcap")
    result, data = checked_dry_run(cfg, faults, lockstep)
    logged = [(m["kind"], m["drone"], m["action"]) for _, m in data.messages("/safety")]
    assert logged == [(e["kind"], e["drone"], e["action"]) for e in result["safety_events"]]
    assert any(m.get("kind") == "fault" for _, m in data.messages("/event"))
    return result, data, logged


# fault, the event it must log (kind, drone, action), drones stopped by it, race end
CASES = [
    ("mocap_dropout_short@1.5", ("mocap_dropout", "ego", "none"), [], "timeout"),
    ("mocap_dropout_long@1.5", ("mocap_stale", "ego", "stop_drone"), ["ego"], "timeout"),
    ("pose_outlier@1.5", ("pose_outlier", "ego", "none"), [], "timeout"),
    ("geofence@1.5", ("geofence", "ego", "stop_drone"), ["ego"], "timeout"),
    ("nan_policy@1.5:opp", ("non_finite", "opp", "stop_drone"), ["opp"], "timeout"),
    ("link_loss@1.5", ("link_lost", "ego", "stop_drone"), ["ego"], "timeout"),
    ("stall_50ms@1.5", ("tick_skipped", None, "none"), [], "timeout"),
    ("stall_200ms@1.5", ("loop_overrun", None, "stop_all"), ["ego", "opp"], "loop_overrun"),
    ("sigterm@1.5", ("operator_kill", None, "stop_all"), ["ego", "opp"], "operator_kill"),
    ("sigint@1.5", ("operator_kill", None, "stop_all"), ["ego", "opp"], "operator_kill"),
    # soft failsafes: the drone lands
    ("mocap_glitchy@1.5", ("mocap_degraded", "ego", "land_drone"), ["ego"], "timeout"),
    ("low_battery@1.5:opp", ("low_battery", "opp", "land_drone"), ["opp"], "timeout"),
    ("operator_land@1.5", ("operator_land", None, "land_all"), ["ego", "opp"], "timeout"),
]
HARD_ENDS = ("loop_overrun", "operator_kill")


def check_landings(result, track_name="lemniscate"):
    """Every drone that was not cut landed: on the ground within 5 s of its landing's start (plus the
    time it held for another drone's path), at most 0.5 m/s down, inside the arena, on its spot; the
    result says why it landed."""
    from cfrace.track import load_track
    arena = load_track(track_name).arena
    out = {}
    for d in result["drones"]:
        land = d["landing"]
        if d["stop_kind"] != "landed":
            continue
        assert land["down"] and land["t"] is not None and land["t"] < 5.0 + land.get("held_s", 0.0), land
        assert abs(land["vz_mps"]) <= 0.5, land
        x, y, _ = land["place"]
        assert arena.x[0] <= x <= arena.x[1] and arena.y[0] <= y <= arena.y[1], land
        assert abs(x - land["spot"][0]) < 0.15 and abs(y - land["spot"][1]) < 0.15, land
        assert result["landings"][d["name"]] == land
        out[d["name"]] = land["reason"]
    return out


@pytest.mark.parametrize("fault, event, stopped, end", CASES, ids=[c[0] for c in CASES])
def test_fault_lockstep(pols, tmp_path, fault, event, stopped, end):
    result, data, logged = run(pols, tmp_path, fault)
    assert event in logged, logged
    assert result["end"] == end
    landed = check_landings(result)
    by_fault = {d["name"] for d in result["drones"] if d["stop_kind"] == event[0] or landed.get(d["name"]) == event[0]}
    assert by_fault == set(stopped), result["drones"]
    if end not in HARD_ENDS:   # everyone else landed: at the race's end, or when the other drone fell in its way
        assert {n for n, why in landed.items() if why in ("race_end", "opponent_down")} \
            == {"ego", "opp"} - set(stopped), landed
    assert sorted(m["drone"] for _, m in data.messages("/landing")) == [d["name"] for d in result["drones"]
                                                                        if d["landing"] and "down" in d["landing"]]
    t_event = next(e["t"] for e in result["safety_events"] if (e["kind"], e["drone"], e["action"]) == event)
    assert 1.5 <= t_event < 2.6      # low_battery: after low_battery_s (1 s) below the limit
    if fault.startswith("link_loss"):
        # the stop cannot reach the drone: the firmware's own watchdog turned the motors off
        assert result["drones_final"][0]["watchdog"] == "shutdown"
        assert 1.9 <= t_event <= 2.1               # silence for link_timeout_s = 0.5 s
    if fault.startswith("mocap_dropout_long"):
        assert t_event == pytest.approx(1.5 + 0.15, abs=0.02)   # mocap_stale_s = 0.15 s
    if fault.startswith(("sigterm", "sigint")):
        assert result["operator_kill"] == ("SIGTERM" if "term" in fault else "SIGINT")
        assert result["duration_s"] < 1.6
    if not stopped:   # rode through: the drones flew on to the end at their height (then landed)
        z = [m["cf1"]["pos"][2] for t, m in data.messages("/estimate") if t < 3.0]
        assert min(z[-50:]) > 0.6


def test_fault_specs():
    fs = parse_faults("geofence@2,link_loss@3.5:opp")
    assert [(f.kind, f.t, f.drone) for f in fs] == [("geofence", 2.0, "ego"), ("link_loss", 3.5, "opp")]
    for bad in ("geofence", "warp@1", "geofence@x", "geofence@1:me", "geofence@-1"):
        with pytest.raises(ConfigError, match="--faults"):
            parse_faults(bad)


def test_faults_real_time_through_cflib(pols, tmp_path):
    """Real time, real cflib over UDP: a real link loss (a relay drops every datagram), a NaN
    policy and a 50 ms stall, in one race."""
    result, data, logged = run(pols, tmp_path, "stall_50ms@0.8,link_loss@1.0:opp,nan_policy@1.2",
                               lockstep=False, timeout_s=3.0)
    assert ("link_lost", "opp", "stop_drone") in logged and ("non_finite", "ego", "stop_drone") in logged
    assert ("tick_skipped", None, "none") in logged
    assert result["end"] == "all_stopped"
    lost = next(e for e in result["safety_events"] if e["kind"] == "link_lost")
    assert 1.3 <= lost["t"] <= 1.8                     # silence detected after ~0.5 s
    assert result["drones_final"][1]["watchdog"] == "shutdown"


def _dry_run_process(pols, tmp_path):
    log = tmp_path / "f.mcap"
    cmd = [sys.executable, "-c", "from cfrace.cli.main import main; main()", "sim", "dry-run",
           "--track", "lemniscate", "--ego", pols["ego"], "--opp", pols["opp"], "--profile", PROFILE,
           "--quiet", "--timeout-s", "30", "--log", str(log), "--json", str(tmp_path / "r.json")]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:   # wait until the race is running (the log grows)
        if log.exists():
            try:
                if read_log(log).count("/timing") > 100:
                    return proc, log
            except Exception:
                pass
        if proc.poll() is not None:
            raise AssertionError(proc.stderr.read())
        time.sleep(0.2)
    proc.kill()
    raise AssertionError("the dry-run did not start")


@pytest.mark.slow
@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["SIGTERM", "Ctrl-C"])
def test_real_signal_mid_race_stops_everything(pols, tmp_path, sig, code):
    import json

    proc, log = _dry_run_process(pols, tmp_path)
    os.kill(proc.pid, sig)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == code, err
    result = json.loads((tmp_path / "r.json").read_text())
    assert result["end"] == "operator_kill" and result["operator_kill"] == signal.Signals(sig).name
    for d in result["drones_final"]:
        assert d["motors_off"] and not d["armed"], d
    data = read_log(log)
    assert data.complete and data.summary["operator_kill"] == signal.Signals(sig).name
    assert ("operator_kill", None, "stop_all") in [(m["kind"], m["drone"], m["action"])
                                                   for _, m in data.messages("/safety")]
    stops = [m for _, m in data.messages("/event") if m.get("kind") == "stop"]
    assert {m["drone"] for m in stops} == {"ego", "opp"}
    assert "operator_kill" in out


def test_an_exception_mid_race_still_stops_everything_and_closes_the_log(pols, tmp_path):
    from cfrace.rehearsal.dryrun import sim_race
    from cfrace.rehearsal.faults import FaultInjector
    from cfrace.flight.setup import resolve_race
    from cfrace.simcf.firmware import SimFleet

    class Boom(FaultInjector):
        def filter_action(self, drone, act, t):
            if t >= 1.2:
                raise RuntimeError("policy runtime exploded")
            return act

    cfg = FlightConfig(track="lemniscate", ego=pols["ego"], opp=pols["opp"], profile=PROFILE, quiet=True,
                       timeout_s=3.0, log=tmp_path / "f.mcap")
    fleet = SimFleet("lemniscate", PROFILE, 2, obstacles=False)
    with pytest.raises(RuntimeError, match="exploded"):
        sim_race(resolve_race(cfg), fleet, injector=Boom([], {})).to_json()
    for _ in range(5):
        fleet.advance(0.01)
    for i in range(2):
        s = fleet.status(i)
        assert s["thrust"] == 0.0 and not s["armed"], s
    data = read_log(tmp_path / "f.mcap")
    assert data.complete and "exploded" in data.summary["error"]
    assert {m["drone"] for _, m in data.messages("/event") if m.get("kind") == "stop"} == {"ego", "opp"}


@pytest.mark.slow
def test_bench_loop_against_a_sim_serve_process():
    """`cfrace bench loop`: `cfrace sim serve` in its own process, the fly code over cflib/UDP
    and the sim:// pose stream; every figure is measured."""
    from cfrace.rehearsal.loop_timing import bench_loop

    r = bench_loop(2.0, profile=PROFILE, floor_s=1.0)
    loop = r["loop"]
    floor = r["floor"]   # the machine's floor: a loop with no work, same CPU and priority
    assert floor["ticks"] == 100 and floor["loop_cpu"] == r["loop_cpu"]
    assert 0 < floor["late_ms"]["p50"] <= floor["late_ms"]["p99"] <= floor["late_ms"]["max"]
    assert r["end"] == "timeout" and loop["ticks"] + loop["skipped"] >= 195
    for key in ("compute_ms", "compute_cpu_ms", "period_jitter_ms", "late_ms"):
        assert 0 < loop[key]["p50"] <= loop[key]["p99"] <= loop[key]["max"], key
    assert set(loop["inference_ms"]) == {"ego", "opp"} and loop["inference_p99_ms"] > 0
    assert r["prewarm_s"] == 0.003 and 0 < loop["prewarm_ms"]["p50"] <= loop["prewarm_ms"]["max"]   # warm-up ran
    assert loop["prewarm_calls_mean"] >= 1.0
    assert set(r["goals_met"]) == {"compute_p99_ms", "period_jitter_p99_ms", "inference_p99_ms"}
    assert all(e["action"] == "none" for e in r["safety_events"])
    from test_flight_realtime import fifo_permitted
    assert r["rt_fifo"] == fifo_permitted() and floor["rt_fifo"] == r["rt_fifo"]   # default: FIFO where permitted
    if r["loop_cpu"] is not None:   # pinned (two or more CPUs): the simulated drones run elsewhere
        assert r["loop_cpu"] == max(os.sched_getaffinity(0)) and r["loop_cpu"] not in r["sim_serve_cpus"]
