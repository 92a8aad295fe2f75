"""Whole races through the flight stack (lockstep dry-run, shipped policies) that end on the ground:
every drone lands softly inside the arena; with --start hover the drones take off to their start
positions first and hold them within 0.1 m; ours still beats DS."""

import subprocess
import sys
import time
from pathlib import Path

import pytest

from cfrace.flight.config import FlightConfig
from cfrace.rehearsal.dryrun import dry_run
from cfrace.flight.log.writer import read_log
from cfrace.rehearsal.replay import replay_log
from test_flight_faults import check_landings


@pytest.mark.parametrize("start", ["ground", "hover"])
def test_race_ends_with_every_drone_landed(tmp_path, start):
    cfg = FlightConfig(track="lemniscate", ego="ours", opp="ds", profile="cf2x_paper", laps=1, quiet=True,
                       timeout_s=30.0, log=tmp_path / "r.mcap", start=start)
    result = dry_run(cfg, lockstep=True).to_json()
    assert result["end"] == "finished" and result["winner"] == "ego", result["laps"]
    assert check_landings(result) == {"ego": "race_end", "opp": "race_end"}
    assert all(not d["crashed"] and d["motors_off"] for d in result["drones_final"])
    if start == "hover":
        assert max(result["hover_start"]["hold_error_m"]) <= 0.1
    else:
        assert "hover_start" not in result
    data = read_log(tmp_path / "r.mcap")
    landed = {m["drone"]: m for _, m in data.messages("/landing")}
    assert set(landed) == {"ego", "opp"} and all(abs(m["vz_mps"]) <= 0.5 for m in landed.values())
    texts = [m.get("text", "") for _, m in data.messages("/event")]
    assert sum(t.startswith("go_to") for t in texts) == 2 and sum(t == "notify_stop" for t in texts) == 2
    # the replay reproduces the race and its end, where DS flies on through its gate on its policy
    # while ours has begun to land
    first_landing = min(t for t, m in data.messages("/event") if m["kind"] == "landing")
    assert max(t for t, _ in data.messages("/obs")) > first_landing
    r = replay_log(tmp_path / "r.mcap")
    assert r["identical"] and r["observations"] > 0, r


#: the ours file of 2026-12-02 (pipeline stage ours_lemniscate_twin), with which the race ends below were found
OURS_STAGE5 = str(Path(__file__).parent / "data" / "ours_lemniscate_stage5.onnx")

#: race ends (ego, opp, profile, the timeout s) of lockstep races at which a landing used to hit a
#: gate frame: ds against that ours on cf2x_paper braking into the gate ahead (2.83: the crash unseen, the
#: drone dropped less than the outlier limit; 6.79: turning into the gate from the side), or stopping
#: just in front of it and then flying the go-to along its frame (3.34) or through it (3.01). Each
#: crash showed as pose outliers and a speed stop, as in the real-time flight against `sim serve`
CRASHING_ENDS = (("ds", OURS_STAGE5, "cf2x_paper", 2.83), ("ds", OURS_STAGE5, "cf2x_paper", 3.01),
                 ("ds", OURS_STAGE5, "cf2x_paper", 3.34), ("ds", OURS_STAGE5, "cf2x_paper", 6.79))


@pytest.mark.parametrize("ego, opp, profile, timeout_s", CRASHING_ENDS)
def test_race_end_landings_keep_clear(ego, opp, profile, timeout_s):
    cfg = FlightConfig(track="lemniscate", ego=ego, opp=opp, profile=profile, laps=3, quiet=True,
                       timeout_s=timeout_s)
    result = dry_run(cfg, lockstep=True).to_json()
    assert result["end"] == "timeout"
    assert not [d for d in result["drones_final"] if d["crashed"]], result["drones_final"]
    assert not [e for e in result["safety_events"] if e["action"] != "none" or e["kind"] == "pose_outlier"], \
        result["safety_events"]
    assert check_landings(result) == {"ego": "race_end", "opp": "race_end"}


def test_a_drone_flying_through_after_the_race_scores_nothing_more():
    """At 2.83 s both drones would brake into the gate ahead and fly through it before they land
    (above); the result counts the gates and laps as the race ended, as the same race without landing."""
    results = []
    for landing in (True, False):
        cfg = FlightConfig(track="lemniscate", ego="ds", opp=OURS_STAGE5, profile="cf2x_paper", laps=3, quiet=True,
                           timeout_s=2.83, landing=landing)
        results.append(dry_run(cfg, lockstep=True).to_json())
    tally = [[(d["name"], d["gates_passed"], d["laps"], d["lap_times"]) for d in r["drones"]] for r in results]
    assert tally[0] == tally[1] and results[0]["end"] == results[1]["end"] == "timeout"
    assert check_landings(results[0]) == {"ego": "race_end", "opp": "race_end"}


def test_no_landing_keeps_the_old_stop(tmp_path):
    cfg = FlightConfig(track="lemniscate", ego="ours", opp="ds", profile="cf2x_paper", laps=1, quiet=True,
                       timeout_s=30.0, landing=False)
    result = dry_run(cfg, lockstep=True).to_json()
    assert result["end"] == "finished" and all(d["landing"] is None for d in result["drones"])


def test_fly_check_against_sim_serve(tmp_path):
    """`cfrace fly --check` (pre-flight checks) against `cfrace sim serve` in another process, real time."""
    serve = subprocess.Popen([sys.executable, "-m", "cfrace", "sim", "serve", "--track", "lemniscate", "--drones",
                              "2", "--port", "19760", "--decks", "none", "--profile", "cf21bl"],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        t_end = time.monotonic() + 30
        while "Ctrl-C" not in serve.stdout.readline():
            assert time.monotonic() < t_end and serve.poll() is None
        cmd = [sys.executable, "-m", "cfrace", "fly", "--track", "lemniscate", "--ego", "ours", "--opp", "ds",
               "--uris", "udp://127.0.0.1:19760,udp://127.0.0.1:19761", "--mocap", "sim://127.0.0.1:19759",
               "--profile", "cf21bl", "--check", "--json", str(tmp_path / "check.json")]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=tmp_path)
        assert done.returncode == 0, done.stdout + done.stderr
        lines = done.stdout.splitlines()
        assert sum(line.startswith("ok") for line in lines) == 10, lines
        bad = subprocess.run(cmd[:-2] + ["--bodies", "cf2,cf1"], capture_output=True, text=True, timeout=120,
                             cwd=tmp_path)
        assert bad.returncode == 2 and "rose most" in bad.stdout, bad.stdout + bad.stderr
    finally:
        serve.terminate()
        serve.wait(10)


def test_real_time_race_lands_through_the_link_keeper(tmp_path):
    """Real time, real cflib over UDP through the link keeper process: the poses, the go-to, the
    notify-stop and the land reach the simulated drones, which land."""
    from test_flight_faults import PROFILE
    from cfrace.rehearsal.hold_policy import make_hold_policy
    ego = make_hold_policy(tmp_path / "ego.onnx", "race42", "lemniscate", False)
    opp = make_hold_policy(tmp_path / "opp.onnx", "solo36", "lemniscate", False)
    cfg = FlightConfig(track="lemniscate", ego=str(ego), opp=str(opp), profile=PROFILE, quiet=True, timeout_s=2.0,
                       log=tmp_path / "rt.mcap")
    result = dry_run(cfg, lockstep=False).to_json()
    assert result["end"] == "timeout"
    assert check_landings(result) == {"ego": "race_end", "opp": "race_end"}
    assert result["loop"]["poses_sent"] > 300


def test_a_field_lands_at_the_race_end():
    """Four drones on the lemniscate, the race ended at 2 s (a clean end of the race-end scan in
    docs/flight.md, "Race ends in a field"): every drone lands,
    none crashed and no safety event acted after the end."""
    cfg = FlightConfig(track="lemniscate", ego="ours", opp="ds", policies=("ours", "ds", "ours", "ds"),
                       profile="cf2x_paper", laps=3, quiet=True, timeout_s=2.0)
    r = dry_run(cfg, lockstep=True).to_json()
    assert r["end"] == "timeout"
    assert not [f["body"] for f in r["drones_final"] if f["crashed"]]
    assert not [e for e in r["safety_events"] if e["action"] != "none" and e["t"] >= 2.0]
    assert [d["stop_kind"] for d in r["drones"]] == ["landed"] * 4
    assert r["loop"]["compute_cpu_ms"]["max"] > 0.0
