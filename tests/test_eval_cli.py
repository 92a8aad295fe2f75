"""`cfrace eval | race | tournament`: the commands, the files they write (valid JSON and PNG,
markdown), short-name resolution and one-line refusals of policies that do not fit."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cfrace.cli.main import app
from cfrace.errors import PolicyError
from cfrace.evaluate.entrants import common_profile, load_entrant, load_entrants
from cfrace.policygraph import build_model
from cfrace.track import load_track

from policyfiles import make_test_policy
from test_eval_run import TRACK_YAML, tilt_policy

PNG = b"\x89PNG\r\n\x1a\n"
CFRACE = Path(sys.executable).with_name("cfrace")
runner = CliRunner()
SPAWN = "spawn:\n  gate_distance: [0.6, 1.0]\n  lateral: 0.1\n"


def png_size(path: Path) -> tuple[int, int]:
    data = Path(path).read_bytes()
    assert data[:8] == PNG and data[12:16] == b"IHDR", f"{path} is not a PNG"
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("evalcli")
    track = tmp / "straight.yaml"
    track.write_text(TRACK_YAML + SPAWN)
    pols = tmp / "policies"
    pols.mkdir()
    tilt_policy(pols / "ds_straight.onnx", 30.0)                    # short name "ds"
    tilt_policy(pols / "ours_straight.onnx", 20.0, "race42")         # short name "ours"
    slow = tilt_policy(tmp / "slow.onnx", 12.0)
    return tmp, track, slow


@pytest.fixture
def short_names(env, monkeypatch):
    monkeypatch.setattr("cfrace.policy.POLICIES_DIR", env[0] / "policies")


def invoke(*args):
    result = runner.invoke(app, [str(a) for a in args], env={"COLUMNS": "200"})
    assert result.exit_code == 0, (result.output, result.exception)
    return result


def test_eval_writes_json_markdown_and_trajectory_pngs(env, short_names):
    tmp, track, slow = env
    out = tmp / "eval"
    r = invoke("eval", "ds", slow, "ours", "--track", track, "--runs", 6, "--laps", 1, "--seed", 2,
               "--json", out / "e.json", "--md", out / "e.md", "--plot", out / "plots")
    data = json.loads((out / "e.json").read_text())
    assert [p["name"] for p in data["policies"]] == ["ds", "slow", "ours"]
    assert data["runs"] == 6 and data["laps"] == 1 and data["seed"] == 2
    for row in data["policies"]:
        for key in ("success_rate", "lap_time_s", "avg_speed_mps", "collisions", "crashes", "timeouts"):
            assert key in row
        assert 0.0 <= row["success_rate"] <= 1.0
    ds, sl, ours = data["policies"]
    assert ds["success_rate"] > 0 and ds["lap_time_s"] < sl["lap_time_s"]       # 30 deg flies faster than 12
    assert ours["obs_layout"] == "race42" and ours["success_rate"] > 0           # flies alone, parked opponent
    md = (out / "e.md").read_text()
    assert "| Avg. TTC [s] | Avg. speed [m/s] | Collisions | Success [%]" in md
    assert sum(line.startswith("| ds |") or line.startswith("| slow |") for line in md.splitlines()) == 2
    pngs = sorted((out / "plots").glob("*.png"))
    assert [p.name for p in pngs] == ["trajectory_ds.png", "trajectory_ours.png", "trajectory_slow.png"]
    assert all(min(png_size(p)) > 300 for p in pngs)
    assert "ds" in r.output and "Success" in r.output


def test_eval_single_policy_json_has_the_metrics_at_top_level(env):
    tmp, track, slow = env
    invoke("eval", slow, "--track", track, "--runs", 2, "--laps", 1, "--json", tmp / "one.json")
    data = json.loads((tmp / "one.json").read_text())
    for key in ("success_rate", "lap_time_s", "avg_speed_mps", "collisions"):
        assert data[key] == data["policies"][0][key]


def test_race_json_rates_and_plots(env, short_names):
    tmp, track, slow = env
    invoke("race", "--track", track, "--ego", "ds", "--opp", slow, "--races", 6, "--laps", 1,
           "--json", tmp / "r.json", "--plot", tmp / "race")
    data = json.loads((tmp / "r.json").read_text())
    total = data["ego_win_rate"] + data["opp_win_rate"] + data["draw_rate"]
    assert total == pytest.approx(1.0)
    assert data["swapped_races"] == 3 and data["races"] == 6
    assert data["ego_win_rate"] > data["opp_win_rate"]           # the faster policy wins more
    assert sum(data["counts"].values()) == 6
    sp = data["speed_profile"]
    assert sp["vs_live_opponent"]["max_mps"] > 0 and sp["vs_crashed_opponent"]["max_mps"] > 0
    for name in ("race_trajectories.png", "speed.png"):
        assert min(png_size(tmp / "race" / name)) > 300


def test_race_pairs_a_42d_policy_with_a_36d_one(env, short_names):
    tmp, track, slow = env
    invoke("race", "--track", track, "--ego", "ours", "--opp", "ds", "--races", 2, "--laps", 1,
           "--json", tmp / "mixed.json")
    data = json.loads((tmp / "mixed.json").read_text())
    assert data["ego_policy"] == "ours" and data["opp_policy"] == "ds"


def test_tournament_matrix_json_and_heatmap(env, short_names):
    tmp, track, slow = env
    invoke("tournament", "ds", "ours", slow, "--track", track, "--races", 4, "--laps", 1,
           "--json", tmp / "t.json", "--heatmap", tmp / "t.png")
    data = json.loads((tmp / "t.json").read_text())
    assert data["policies"] == ["ds", "ours", "slow"]
    win, draw = data["win_rate"], data["draw_rate"]
    for i in range(3):
        assert win[i][i] is None and draw[i][i] is None
        for j in range(3):
            if i != j:
                assert win[i][j] + win[j][i] + draw[i][j] == pytest.approx(1.0)
                assert draw[i][j] == draw[j][i]
    assert win[0][2] > win[2][0]                                 # 30 deg beats 12 deg
    assert png_size(tmp / "t.png")[0] > 300


def test_mismatched_policies_are_refused(env, tmp_path):
    _, track_path, slow = env
    track = load_track(track_path)
    lem = make_test_policy(tmp_path / "lem.onnx", "solo36", "lemniscate", False)
    with pytest.raises(PolicyError, match="trained on track 'lemniscate', not 'straight'"):
        load_entrant(lem, track, False)
    with pytest.raises(PolicyError, match="trained without obstacles"):
        load_entrant(slow, track, True)
    import numpy as np
    import onnx

    meta = dict(__import__("cfrace.policy", fromlist=["OnnxPolicy"]).OnnxPolicy(slow).meta)
    bad = tmp_path / "bad.onnx"   # a 42-input graph that claims the 36-D layout
    onnx.save_model(build_model([("linear", np.zeros((4, 42), np.float32), np.zeros(4, np.float32))], None, None,
                                meta, 42), str(bad))
    with pytest.raises(PolicyError, match="obs_dim is 36"):
        load_entrant(bad, track, False)
    fast = dict(meta, policy_hz=100.0)
    onnx.save_model(build_model([("linear", np.zeros((4, 36), np.float32), np.zeros(4, np.float32))], None, None,
                                fast, 36), str(tmp_path / "100hz.onnx"))
    with pytest.raises(PolicyError, match="runs at 100 Hz"):
        load_entrant(tmp_path / "100hz.onnx", track, False)
    other = make_test_policy(tmp_path / "bl.onnx", "solo36", "straight", False, profile="cf21bl")
    with pytest.raises(PolicyError, match="different drone profiles"):
        common_profile(load_entrants([str(slow), str(other)], track, False))


@pytest.mark.slow  # a fresh process imports torch and onnxruntime: 7-10 s on the loaded 2-core machine
def test_cli_refusal_is_one_line_with_exit_code_2(env, tmp_path):
    _, track, _ = env
    lem = make_test_policy(tmp_path / "lem.onnx", "race42", "lemniscate", False)
    proc = subprocess.run([str(CFRACE), "race", "--track", str(track), "--ego", str(lem), "--opp", str(lem)],
                          capture_output=True, text=True, timeout=120, env=dict(os.environ, COLUMNS="200"))
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "not 'straight'" in lines[0]


def test_short_name_without_a_shipped_policy_is_refused(env, short_names):
    _, track, _ = env
    result = runner.invoke(app, ["eval", "ss", "--track", str(track)])
    assert result.exit_code != 0 and isinstance(result.exception, PolicyError)
    assert "no shipped policy ss_straight.onnx" in str(result.exception)


def test_shipped_ds_policy_completes_laps_on_the_lemniscate():
    from cfrace.evaluate.single import evaluate

    r = evaluate(["ds"], "lemniscate", runs=6, laps=1, seed=0)
    row = r.rows[0]
    assert row["success_rate"] >= 0.5, row
    assert 3.0 < row["lap_time_s"] < 10.0 and row["avg_speed_mps"] > 2.0
