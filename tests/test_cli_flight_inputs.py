"""Bad input to `cfrace fly` and `cfrace sim dry-run` that a hurried user types: one line, exit 2,
nothing connected or flown first (found by following the docs as a newcomer)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

CFRACE = Path(sys.executable).with_name("cfrace")
NOWHERE = ["--mocap", "sim://127.0.0.1:9", "--uris", "udp://127.0.0.1:7,udp://127.0.0.1:8", "--track", "lemniscate"]


def run(*args, cwd: Path):
    env = dict(os.environ, COLUMNS="200")
    return subprocess.run([str(CFRACE), *args], capture_output=True, text=True, env=env, timeout=240, cwd=cwd)


def one_line_refusal(r, *words):
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stderr + r.stdout and r.stderr.count("\n") == 1, r.stderr
    assert all(w in r.stderr for w in words), r.stderr


@pytest.mark.parametrize("value, words", [("5", ["0 to 1"]), ("-1", ["0 to 1"]), ("0,0", ["distinct"]),
                                          ("a", ["drone indices"])])
def test_a_bad_hover_drones_is_refused_before_anything_connects(tmp_path, value, words):
    r = run("fly", *NOWHERE, "--ego", "ours", "--opp", "ds", "--hover", f"--hover-drones={value}", cwd=tmp_path)
    one_line_refusal(r, "--hover-drones", *words)
    assert "nothing listens" not in r.stderr        # refused before the links (nothing listens there)


def test_hover_drones_without_hover_does_not_fly_a_race(tmp_path):
    r = run("fly", *NOWHERE, "--ego", "ours", "--opp", "ds", "--hover-drones", "1", cwd=tmp_path)
    one_line_refusal(r, "--hover-drones", "--hover")


def test_a_log_path_under_a_file_is_refused_before_anything_flies(tmp_path):
    (tmp_path / "room.yaml").write_text("laps: 1\n")
    r = run("sim", "dry-run", "--track", "lemniscate", "--ego", "ours", "--opp", "ds", "--lockstep", "--quiet",
            "--log", "room.yaml/r.mcap", cwd=tmp_path)
    one_line_refusal(r, "--log", "room.yaml/r.mcap")
    r = run("fly", *NOWHERE, "--ego", "ours", "--opp", "ds", "--log", "room.yaml/r.mcap", cwd=tmp_path)
    one_line_refusal(r, "--log")
    assert not list(tmp_path.glob("*.stops.jsonl"))            # the link keeper never started


def test_the_config_files_policies_and_typed_ego_opp_do_not_mix_and_the_dry_run_flies_the_files(tmp_path):
    """`fly` flew the file's `policies:` and dropped the typed --ego/--opp; the dry-run dropped the
    file's policies: the rehearsal and the flight raced different policies."""
    (tmp_path / "pol.yaml").write_text("policies: [ours, ds, ss]\n")
    one_line_refusal(run("fly", "--config", "pol.yaml", *NOWHERE, "--ego", "ss", "--opp", "dm", cwd=tmp_path),
                     "pol.yaml", "'policies:'", "--ego/--opp")
    one_line_refusal(run("sim", "dry-run", "--config", "pol.yaml", "--track", "lemniscate", "--ego", "ss", "--opp",
                         "dm", "--lockstep", cwd=tmp_path), "pol.yaml", "'policies:'")
    (tmp_path / "pair.yaml").write_text("ego: ours\nopp: ds\n")
    one_line_refusal(run("fly", "--config", "pair.yaml", *NOWHERE, "--policies", "ours,ds,ss", cwd=tmp_path),
                     "pair.yaml", "--policies")
    r = run("sim", "dry-run", "--config", "pol.yaml", "--track", "lemniscate", "--lockstep", "--quiet", "--laps", "1",
            "--json", "r.json", cwd=tmp_path)
    assert r.returncode in (0, 3), r.stderr
    assert [d["method"] for d in json.loads((tmp_path / "r.json").read_text())["drones"]] == ["ours", "ds", "ss"]


def test_config_files_refuse_zero_limits_repeated_keys_and_non_text(tmp_path):
    (tmp_path / "t0.yaml").write_text("safety:\n  tilt_max_deg: 0\n")
    one_line_refusal(run("sim", "dry-run", "--config", "t0.yaml", "--track", "lemniscate", "--ego", "ours", "--opp",
                         "ds", "--lockstep", cwd=tmp_path), "t0.yaml", "safety.tilt_max_deg", "> 0")
    one_line_refusal(run("fly", *NOWHERE, "--ego", "ours", "--opp", "ds", "--speed-max-mps", "0", cwd=tmp_path),
                     "speed_max_mps", "(0, 50]")
    (tmp_path / "dup.yaml").write_text("safety:\n  speed_max_mps: 8\n  speed_max_mps: 3\n")
    one_line_refusal(run("sim", "dry-run", "--config", "dup.yaml", "--track", "lemniscate", "--ego", "ours", "--opp",
                         "ds", "--lockstep", cwd=tmp_path), "dup.yaml", "line 3", "'speed_max_mps' is given twice")
    (tmp_path / "latin1.yaml").write_bytes("laps: 1\n# caf\xe9\n".encode("latin-1"))
    one_line_refusal(run("fly", "--config", "latin1.yaml", *NOWHERE, "--ego", "ours", "--opp", "ds", cwd=tmp_path),
                     "latin1.yaml", "not a YAML text file")
    one_line_refusal(run("tracks", "show", "latin1.yaml", cwd=tmp_path), "latin1.yaml", "not a YAML text file")


def test_report_and_log_outputs_under_a_file_and_an_empty_seed_list_are_refused(tmp_path):
    (tmp_path / "room.yaml").write_text("laps: 1\n")
    one_line_refusal(run("reproduce", "--quick", "--out", "room.yaml", cwd=tmp_path), "--out", "not a folder")
    one_line_refusal(run("reproduce", "--quick", "--test-seeds", ",", "--out", "rp", cwd=tmp_path), "--test-seeds",
                     "no seed")
    assert not (tmp_path / "rp").exists()
    one_line_refusal(run("log", "info", "any.mcap", "--json", "room.yaml/x.json", cwd=tmp_path), "--json")


def test_replay_of_a_log_cut_before_its_first_tick_and_a_bad_json_path(tmp_path):
    r = run("sim", "dry-run", "--track", "lemniscate", "--ego", "ours", "--opp", "ds", "--lockstep", "--quiet",
            "--laps", "1", "--log", "f.mcap", cwd=tmp_path)
    assert r.returncode in (0, 3), r.stderr
    (tmp_path / "cut.mcap").write_bytes((tmp_path / "f.mcap").read_bytes()[:6000])
    r = run("sim", "replay", "cut.mcap", cwd=tmp_path)
    assert r.returncode == 1 and "nothing to compare" in r.stdout and "Traceback" not in r.stderr, r.stdout + r.stderr
    (tmp_path / "room.yaml").write_text("laps: 1\n")
    one_line_refusal(run("sim", "replay", "f.mcap", "--json", "room.yaml/x.json", cwd=tmp_path), "--json")


def test_two_body_names_for_three_drones_are_refused_not_filled_in(tmp_path):
    one_line_refusal(run("sim", "dry-run", "--track", "lemniscate", "--policies", "ours,ds,ours", "--bodies", "cf1,cf2",
                         "--lockstep", "--quiet", cwd=tmp_path), "bodies: need 3")


def test_a_foxglove_port_in_use_is_refused_before_any_link_opens(tmp_path):
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        r = run("sim", "dry-run", "--track", "lemniscate", "--ego", "ours", "--opp", "ds", "--quiet",
                "--foxglove", str(port), "--log", "f.mcap", cwd=tmp_path)
    one_line_refusal(r, str(port))
    assert not list(tmp_path.glob("*.stops.jsonl"))    # the link keeper never started: nothing was sent


def test_a_mistyped_profile_names_the_known_ones_and_trained(tmp_path):
    one_line_refusal(run("sim", "dry-run", "--track", "lemniscate", "--ego", "ours", "--opp", "ds", "--lockstep",
                         "--profile", "traned", cwd=tmp_path), "--profile traned", "cf21bl", "'trained'")


def test_yaml_merge_keys_load_and_may_be_overridden_while_repeated_keys_are_refused(tmp_path):
    from cfrace.errors import ConfigError
    from cfrace.yamlcfg import load_yaml

    f = tmp_path / "m.yaml"
    f.write_text("base: &b {speed_max_mps: 8, tilt_max_deg: 60}\nsafety:\n  <<: *b\n  speed_max_mps: 9\n",
                 encoding="utf-8")
    assert load_yaml(f)["safety"] == {"speed_max_mps": 9, "tilt_max_deg": 60}
    f.write_text("name: café\n", encoding="utf-8")               # UTF-8 whatever the locale
    assert load_yaml(f)["name"] == "café"
    f.write_text("a: 1\nb: 2\na: 3\n")
    with pytest.raises(ConfigError, match="line 3 invalid YAML: key 'a' is given twice"):
        load_yaml(f)


def test_sim_serve_refuses_without_printing_its_banner_first(tmp_path):
    for args in (["--track", "lemniscat"], ["--track", "lemniscate", "--decks", "lighthose"]):
        r = run("sim", "serve", *args, cwd=tmp_path)
        one_line_refusal(r)
        assert r.stdout == "", r.stdout


@pytest.mark.parametrize("args, words", [
    (["--drones", "3", "--bodies", "cf1,cf2"], ["--bodies", "need 3 distinct", "got cf1,cf2"]),
    (["--bodies", "a,a"], ["--bodies", "got a,a"]),
    (["--decks", "foo"], ["--decks", "unknown deck 'foo'"]),
    (["--port", "65535", "--drones", "2"], ["--port", "0..65533"])])
def test_sim_serve_names_the_option_a_bad_value_came_from(tmp_path, args, words):
    r = run("sim", "serve", "--track", "lemniscate", *args, cwd=tmp_path)
    one_line_refusal(r, *words)
    assert "simcf" not in r.stderr


def test_a_body_that_rises_too_little_in_the_check_points_at_the_profile_too():
    import numpy as np

    from cfrace.flight.safety.preflight import PreflightConfig, judge_signal

    q = np.array([1.0, 0.0, 0.0, 0.0])
    still = [(np.array([0.0, 0.0, 0.02]), q)] * 5
    rose = [(np.array([0.0, 0.0, 0.02 + z]), q) for z in (0.0, 0.0005, 0.001, 0.001, 0.0)]
    body = judge_signal({"cf1": rose, "cf2": still}, "cf1", 0, PreflightConfig())[0]
    assert not body.ok and "rose 0.1 cm" in body.detail and "--profile" in body.detail
    swapped = judge_signal({"cf1": still, "cf2": [(p + [0, 0, 0.05], q) for p, q in rose]}, "cf1", 0,
                           PreflightConfig())[0]
    assert not swapped.ok and "'cf2' rose most" in swapped.detail and "--profile" not in swapped.detail
