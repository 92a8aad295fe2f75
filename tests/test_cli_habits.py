"""A lab's first hour (issue 16): defaults that fly, errors that say what to do, standard CLI
habits, one definition of each loop figure, words that fit what happened."""

from __future__ import annotations

import io
import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from cfrace.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
RACE = ["--track", "lemniscate", "--ego", "ours", "--opp", "ds"]


def main_run(args: list[str]) -> None:
    """cfrace in this process, exceptions other than SystemExit propagating."""
    argv, sys.argv = sys.argv, ["cfrace", *args]
    try:
        from cfrace.cli.main import app
        app(args=args, prog_name="cfrace", standalone_mode=False)
    finally:
        sys.argv = argv


def run(args: list[str], capsys=None) -> tuple[int, str, str]:
    """cfrace in this process: (exit code, stdout, stderr); SIGINT/SIGTERM handled as before it
    (a race's command ignores them after the race, as its process is about to exit)."""
    argv, sys.argv = sys.argv, ["cfrace", *args]
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        main()
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    finally:
        sys.argv = argv
        for s, h in handlers.items():
            signal.signal(s, h)
    if capsys is None:
        return code, "", ""
    out = capsys.readouterr()
    return code, out.out, out.err


def cli(args: list[str], timeout: float = 60, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cfrace", *args], capture_output=True, text=True,
                          timeout=timeout, **kw)


def _room_yaml() -> dict:
    """The room.yaml example of docs/flight.md, as written there."""
    text = (ROOT / "docs" / "flight.md").read_text()
    return yaml.safe_load(_dedent(re.search(r"```yaml\n\s*# room.yaml\n(.*?)```", text, re.S).group(1)))


def _dedent(block: str) -> str:
    lines = [line for line in block.splitlines() if line.strip()]
    pad = min(len(line) - len(line.lstrip()) for line in lines)
    return "\n".join(line[pad:] for line in lines)


# 1 -- serve, fly and dry-run agree ------------------------------------------------------------

def test_serve_fly_and_dry_run_agree_on_obstacles_and_profile(tmp_path, capsys):
    from cfrace.cli import flight, sim
    from cfrace.cli.main import app
    import typer.main

    cmd = typer.main.get_command(app)
    serve = cmd.commands["sim"].commands["serve"]
    dry = cmd.commands["sim"].commands["dry-run"]
    fly = cmd.commands["fly"]
    defaults = {c.name: {p.name: p.default for p in c.params} for c in (serve, dry, fly)}
    assert defaults["serve"]["obstacles"] in (False, None)
    assert defaults["dry-run"]["obstacles"] in (False, None) and defaults["fly"]["obstacles"] in (False, None)
    assert flight and sim
    # the dry-run's default profile is fly's, stated in the result with its rule
    code, out, _ = run(["sim", "dry-run", *RACE, "--lockstep", "--timeout-s", "0.3", "--json", "-"], capsys)
    r = json.loads(out)
    assert code == 0 and r["profile"] == "cf21bl" and "default" in r["profile_rule"]
    # one flag takes the policy's training profile instead
    code, out, _ = run(["sim", "dry-run", *RACE, "--lockstep", "--timeout-s", "0.3", "--profile", "trained",
                        "--json", "-"], capsys)
    assert json.loads(out)["profile"] == "cf2x_paper"
    # `sim serve` says what it serves
    proc = subprocess.Popen([sys.executable, "-m", "cfrace", "sim", "serve", "--track", "lemniscate", "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        first = proc.stdout.readline()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=20)
    assert "drone profile cf21bl" in first and "obstacles off" in first


def test_a_race_with_every_drone_stopped_does_not_exit_0(capsys):
    code, out, _ = run(["sim", "dry-run", *RACE, "--lockstep", "--timeout-s", "3", "--json", "-",
                        "--faults", "nan_policy@0.5:ego,nan_policy@0.5:opp"], capsys)
    assert json.loads(out)["end"] == "all_stopped"
    assert code == 3
    # a check that stops every drone at once (the pose/command consistency check here) exits 3 too
    code, out, _ = run(["sim", "dry-run", *RACE, "--lockstep", "--timeout-s", "3", "--json", "-",
                        "--profile", "trained", "--faults", "replay_poses@2"], capsys)
    assert json.loads(out)["end"] == "pose_mismatch" and code == 3


def test_swarm_options_with_the_profile_rule_config_and_json_dash(tmp_path, capsys):
    """N drones (--policies, --drones) with this CLI's profile rule, --config and `--json -`."""
    from cfrace.cli.flight import fly_config

    (tmp_path / "room.yaml").write_text("profile: cf2x_paper\nsafety: {speed_max_mps: 9.0}\n")
    code, out, err = run(["sim", "dry-run", "--track", "lemniscate", "--policies", "ours,ds,ds", "--lockstep",
                          "--config", str(tmp_path / "room.yaml"), "--timeout-s", "1.5",
                          "--faults", "link_loss@0.5:d3", "--json", "-"], capsys)
    r = json.loads(out)
    assert r["profile"] == "cf2x_paper" and "room.yaml" in r["profile_rule"] and "room.yaml" in err
    assert [d["name"] for d in r["drones"]] == ["d1", "d2", "d3"]
    assert {e["drone"] for e in r["safety_events"] if e["kind"] == "link_lost"} == {"d3"}   # parsed by name
    cfg, rule = fly_config(None, "sim://127.0.0.1:1", "trained", track="lemniscate", policies=("ours", "ds", "ds"),
                           uris=tuple(f"udp://127.0.0.1:{19850 + i}" for i in range(3)))
    assert cfg.policies == ("ours", "ds", "ds") and cfg.profile == "cf2x_paper" and "training" in rule
    code, _, err = run(["bench", "loop", "--drones", "2,x", "--foxglove"], capsys)
    assert code == 2 and "--drones" in err and "Traceback" not in err
    # a field the track's start grid cannot hold inside its arena: one line, before any run or drone
    for args in (["bench", "loop", "--drones", "2,8", "--duration-s", "30"],
                 ["sim", "dry-run", "--track", "lemniscate", "--drones", "8", "--ego", "ds", "--lockstep"]):
        code, out, err = run(args, capsys)
        assert code == 2 and "Traceback" not in err and out == "", (args, out, err)
        assert err.strip().endswith("at most 6 drones start there") and err.count("\n") == 1, err


# 2 -- examples fly the shipped policies; messages with enough digits ------------------------

def test_the_room_yaml_example_flies_the_shipped_policies(tmp_path, capsys):
    room = _room_yaml()
    assert room["safety"]["speed_max_mps"] >= 7.0
    (tmp_path / "room.yaml").write_text(yaml.safe_dump(room))
    code, out, _ = run(["sim", "dry-run", *RACE, "--lockstep", "--config", str(tmp_path / "room.yaml"),
                        "--json", "-"], capsys)
    r = json.loads(out)
    assert code == 0 and r["end"] == "finished", r["safety_events"]
    assert r["profile"] == room["profile"]
    finish = sum(r["lap_times"][r["winner"]])      # the landing after the race is not the race
    assert not [e for e in r["safety_events"] if e["action"] != "none" and e["t"] <= finish + 0.05]



def test_the_dry_run_banner_warns_of_the_idle_floor_the_policies_did_not_train_with(capsys):
    _, out, err = run(["sim", "dry-run", *RACE, "--lockstep", "--timeout-s", "0.3"], capsys)
    said = " ".join((out + err).split())
    assert said.count("warning: ") == 2 and "without the idle floor of cf21bl" in said, said
    _, out, err = run(["sim", "dry-run", *RACE, "--lockstep", "--timeout-s", "0.3", "--profile", "cf2x_paper"], capsys)
    assert "warning: " not in out + err

def test_a_speed_stop_prints_two_different_numbers(tmp_path, capsys):
    (tmp_path / "slow.yaml").write_text("safety: {speed_max_mps: 6.0}\n")
    code, out, _ = run(["sim", "dry-run", *RACE, "--lockstep", "--config", str(tmp_path / "slow.yaml"),
                        "--timeout-s", "6", "--json", "-"], capsys)
    speed = [e for e in json.loads(out)["safety_events"] if e["kind"] == "speed"]
    assert speed
    got, limit = map(float, re.match(r"speed ([\d.]+) m/s > ([\d.]+) m/s", speed[0]["detail"]).groups())
    assert got > limit == 6.0


# 3 -- fly's mocap errors say what to do ---------------------------------------------------------

def test_fly_without_mocap_names_the_forms(capsys):
    code, _, err = run(["fly", *RACE, "--uris", "radio://0/80/2M/E7E7E7E7E1,radio://1/90/2M/E7E7E7E7E2"], capsys)
    assert code == 2
    assert "--mocap" in err and "vicon://HOST" in err and "sim://HOST:PORT" in err and err.count("\n") == 1


def test_unreachable_mocap_system_says_what_to_check(tmp_path):
    r = cli(["fly", *RACE, "--uris", "udp://127.0.0.1:9,udp://127.0.0.1:10", "--mocap", "optitrack://localhost",
             "--log", str(tmp_path / "x.mcap")])
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "optitrack server running on 'localhost'" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "x.mcap").exists()


# 4 -- no heavy import before the arguments are checked -----------------------------------------

_MODULES = """
import atexit, sys
atexit.register(lambda: print("HEAVY=" + ",".join(m for m in ("torch", "onnxruntime", "onnx", "matplotlib",
                                                               "tensorboard", "ray", "gymnasium", "pettingzoo",
                                                               "skrl", "motioncapture", "cflib", "mcap", "can")
                                                     if m in sys.modules), file=sys.stderr))
from cfrace.cli.main import main
main()
"""


@pytest.mark.parametrize("args", [["train"], ["fly"], ["sim", "dry-run"], ["eval"], ["race"], ["train", "--help"],
                                  ["bench", "sim", "--help"], ["log", "info"], ["reproduce", "--bogus"],
                                  ["fly", *RACE, "--uris", "udp://127.0.0.1:9,udp://127.0.0.1:10"]])
def test_argument_errors_and_help_import_nothing_heavy(args):
    """Asserted by what is imported (every heavy or optional dependency), not by a wall-clock figure of
    this machine (about half a second on a quiet one): a shared CI VM's speed is no guarantee."""
    r = subprocess.run([sys.executable, "-c", _MODULES, *args], capture_output=True, text=True, timeout=60)
    assert r.returncode in (0, 2), r.stderr
    assert "HEAVY=\n" in r.stderr, r.stderr[-300:]


def test_fly_imports_no_torch():
    """`fly` up to its first contact with the outside (the mocap here): no torch."""
    r = subprocess.run([sys.executable, "-c", _MODULES, "fly", *RACE, "--uris",
                        "udp://127.0.0.1:9,udp://127.0.0.1:10", "--mocap", "replay:///nonexistent.mcap"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "nonexistent" in r.stderr
    heavy = r.stderr.split("HEAVY=")[1].split()
    assert "torch" not in (heavy[0].split(",") if heavy else [])


# 5 -- the README's test command prints a summary ------------------------------------------------

def test_readme_test_command_keeps_the_summary_and_the_slowest_tests():
    """The command CI runs (.ci/run: the first pytest line after "Run the tests") with the project's
    addopts: quiet once (pytest -qq drops the "N passed" line) and the slowest tests listed."""
    import shlex
    import tomllib

    readme = (ROOT / "README.md").read_text()
    cmd = next(line for line in readme[readme.index("Run the tests"):].splitlines() if "pytest" in line)
    addopts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]["addopts"]
    args = shlex.split(cmd) + shlex.split(addopts)
    quiet = sum(a.count("q") for a in args if re.fullmatch(r"-q+", a)) + args.count("--quiet")
    assert quiet <= 1 and any(a.startswith("--durations") for a in args), args


# 6 -- one definition of each loop figure ------------------------------------------------------

def test_log_info_gives_the_figures_the_race_printed(tmp_path, capsys):
    """A flight with a stall (skipped ticks): the JSON result, `log info --json` and the timing plot
    agree on every loop figure, and no period is negative."""
    from cfrace.flight.log.writer import read_log
    from cfrace.flight.log.plots import timing_series

    log = tmp_path / "stall.mcap"
    code, out, _ = run(["sim", "dry-run", *RACE, "--lockstep", "--timeout-s", "2", "--log", str(log),
                        "--faults", "stall_50ms@1.0", "--json", "-"], capsys)
    race = json.loads(out)["loop"]
    assert race["skipped"] >= 4
    code, out, _ = run(["log", "info", str(log), "--json", "-"], capsys)
    info = json.loads(out)["loop"]
    for key in ("period_ms", "period_jitter_ms", "late_ms", "compute_ms", "compute_cpu_ms", "inference_ms",
                "observation_ms", "skipped", "ticks"):
        assert info[key] == race[key], key
    period = timing_series(read_log(log))["period_s"]
    assert (period[1:] > 0).all() and abs(period[1:].max() * 1e3 - race["period_ms"]["max"]) < 1e-3


# 7 -- CLI habits -------------------------------------------------------------------------------

def test_json_dash_prints_to_stdout(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = run(["tracks", "list", "--json", "-"], capsys)
    assert code == 0 and not (tmp_path / "-").exists()
    assert {t["name"] for t in json.loads(out)} >= {"lemniscate", "complex"}
    assert "tracks in" in err                        # the table went to stderr
    code, out, _ = run(["sim", "dry-run", *RACE, "--lockstep", "--timeout-s", "0.2", "--json", "-"], capsys)
    assert json.loads(out)["end"] == "timeout" and not (tmp_path / "-").exists()


def test_version_and_uniform_argument_errors(capsys):
    code, out, _ = run(["--version"], capsys)
    assert code == 0 and re.fullmatch(r"cfrace \d+\.\d+\.\d+\n", out)
    for args in (["fly", "--bogus"], ["train", "--bogus"], ["sim", "dry-run"], ["log", "info"], ["bench", "sim",
                                                                                                 "--worlds"]):
        code, out, err = run(args, capsys)
        assert code == 2, args
        assert err.startswith("error: ") and err.count("\n") == 1 and "╭" not in err + out, (args, err)
        assert "--help" in err


def test_every_option_has_help():
    import typer.main

    from cfrace.cli.main import app

    def walk(cmd, path):
        for name, sub in getattr(cmd, "commands", {}).items():
            yield from walk(sub, f"{path} {name}")
        for p in cmd.params:
            if getattr(p, "param_type_name", "") == "option" and not p.hidden:
                yield path, p

    missing = [f"{path} {p.opts[0]}" for path, p in walk(typer.main.get_command(app), "cfrace")
               if not (p.help or "").strip() and p.opts[0] not in ("--help",)]
    assert not missing, missing


def test_bench_sim_defaults_finish_soon():
    import typer.main

    from cfrace.cli.main import app

    sim = typer.main.get_command(app).commands["bench"].commands["sim"]
    d = {p.name: p.default for p in sim.params}
    assert d["compile"] is False and len(d["worlds"].split(",")) <= 4 and d["modes_opt"] == ""
    from cfrace.sim import ckernel
    if ckernel.available():   # the default measures the C kernel alone (eager at 4096 worlds: minutes)
        calls = []

        class Stop(Exception):
            pass

        def measure_all(sizes, drones, modes, say, **kw):
            calls.append(modes)
            raise Stop

        import cfrace.sim.throughput as sim_bench
        real = sim_bench.measure_all
        sim_bench.measure_all = measure_all
        try:
            with pytest.raises(Stop):
                main_run(["bench", "sim", "--no-peer"])
        finally:
            sim_bench.measure_all = real
        assert calls == [["c"]]


def test_train_says_how_its_step_budget_rounds(tmp_path, capsys, monkeypatch):
    import cfrace.rl.train as rl_train

    def no_training(cfg, resume=None, on_iteration=None):
        raise KeyboardInterrupt   # the budget line was printed; no training in tests

    monkeypatch.setattr(rl_train, "train", no_training)
    code, out, err = run(["train", "--method", "ds", "--track", "lemniscate", "--steps", "50000",
                          "--out", str(tmp_path / "run")], capsys)
    assert code == 130
    text = re.sub(r"\s+", " ", out + err)
    per_it, total = (int(x.replace(",", "")) for x in
                     re.search(r"= ([\d,]+) env steps, so it stops after ([\d,]+)", text).groups())
    assert "50,000 env steps" in text and total % per_it == 0 and 50_000 < total < 50_000 + per_it


def test_log_info_json_and_documented_exit_codes(tmp_path, capsys):
    from tests.test_flight_log import make_log

    good = make_log(tmp_path / "good.mcap")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[:len(good.read_bytes()) // 2])
    code, out, _ = run(["log", "info", str(cut), "--json", "-"], capsys)
    doc = json.loads(out)
    assert code == 0 and doc["truncated"] and doc["topics"]["/estimate"]["count"] > 0
    text = (ROOT / "docs" / "flight-log.md").read_text()
    assert "Exit codes" in text and "truncated" in text


def test_output_paths_that_cannot_be_written_get_one_line(tmp_path, capsys):
    """--png, log plot -o and any other output given where nothing can be written: one line naming
    the option or the path and why, exit 2, no traceback (and no picture written elsewhere)."""
    from tests.test_flight_log import make_log

    log = make_log(tmp_path / "f.mcap")
    a_file = tmp_path / "afile"
    a_file.write_text("x")
    (tmp_path / "plots").mkdir()
    cases = [(["tracks", "show", "lemniscate", "--png", str(tmp_path / "lem")], "give a name ending in .png"),
             (["tracks", "show", "lemniscate", "--png", str(tmp_path / "plots")], "give a name ending in .png"),
             (["tracks", "show", "lemniscate", "--png", "/proc/x.png"], "--png /proc/x.png: cannot write there"),
             (["log", "plot", str(log), "-o", str(a_file)], "not a folder"),
             (["log", "plot", str(log), "-o", "/proc/plots"], "-o /proc/plots: cannot make that folder"),
             (["race", "--track", "lemniscate", "--ego", "ours", "--opp", "ds", "--races", "2", "--plot", "/proc/xx"],
              "--plot /proc/xx: cannot make that folder"),
             (["log", "info", str(tmp_path / "plots")], "error: "),
             (["eval", "ds", "--track", "lemniscate", "--runs", "1", "--md", "/proc/t.md"], "--md /proc/t.md: cannot write")]
    for args, says in cases:
        code, _, err = run(args, capsys)
        assert code == 2 and says in err and "Traceback" not in err and err.count("\n") == 1, (args, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "f.mcap", "plots"]


# 8 -- words that fit ------------------------------------------------------------------------------

def test_ctrl_c_result_says_stopped_by_the_operator(capsys):
    code, out, err = run(["sim", "dry-run", *RACE, "--lockstep", "--faults", "sigint@1.0"], capsys)
    text = re.sub(r"[\s│┃]+", " ", out)     # table cells wrap: words, not phrases
    assert code == 130
    assert "flew to the end" not in text and "operator" in text and "(SIGINT)" in text
    from cfrace.cli.flight import drone_outcome
    assert drone_outcome({"name": "ego", "stopped": True, "stop_t": 1.0, "stop_kind": "operator_kill"},
                         {"end": "operator_kill", "operator_kill": "SIGINT", "duration_s": 1.0}) \
        == "stopped by the operator (SIGINT) at 1.00 s"


def test_link_loss_final_state_does_not_read_as_motors_on(capsys):
    from cfrace.cli.flight import final_state

    s = final_state({"body": "cf1", "motors_off": True, "thrust_counts": 44163, "armed": True,
                     "watchdog": "shutdown"})
    assert "motors off, thrust 44163" not in s and "last setpoint 44163 counts" in s and "watchdog" in s


def test_live_view_ends_on_the_final_frame_and_a_new_line():
    from rich.console import Console

    from cfrace.flight.config import FlightConfig
    from cfrace.rehearsal.dryrun import dry_run

    buf = io.StringIO()
    con = Console(file=buf, force_terminal=False, width=140)
    cfg = FlightConfig(track="lemniscate", ego="ours", opp="ds", timeout_s=1.37, quiet=False, profile="cf21bl")
    r = dry_run(cfg, lockstep=True, console=con)
    text = buf.getvalue()
    frames = re.findall(r"t = +([\d.]+) s", text)
    assert float(frames[-1]) == pytest.approx(r.duration_s, abs=0.051)
    assert text.endswith("\n")


def test_race_plot_panels_name_different_races():
    from cfrace.evaluate.plots import _race_name

    assert _race_name(3, 50) != _race_name(53, 50)


def test_readme_and_docs_wording():
    readme = (ROOT / "README.md").read_text()
    assert "`cfrace sim replay" in readme
    assert "half a lap" not in readme + (ROOT / "docs" / "flight.md").read_text()


def test_the_profile_rule_says_where_the_profile_came_from():
    """--profile wins over the flight config file's profile:, which wins over the default; the result
    line names the source (`profile: in FILE` for the file, not "--profile")."""
    from cfrace.cli.common import choose_profile
    from cfrace.track import load_track

    room = {"profile": "cf2x_paper"}
    assert choose_profile(None, room=room, config="room.yaml") == ("cf2x_paper", "profile: in room.yaml")
    assert choose_profile("cf21bl", room=room, config="room.yaml") == ("cf21bl", "--profile")
    assert choose_profile(None, room={}, config="room.yaml")[1].startswith("the default")
    name, rule = choose_profile(None, load_track("lemniscate"), "ours", False, {"profile": "trained"}, "room.yaml")
    assert name == "cf2x_paper" and rule == "the ego policy's training profile"


def test_cfrace_warnings_are_one_line_and_others_keep_their_form(tmp_path):
    """A cfrace warning (the simulator's slower fallback for 17 drones) reads `warning: ...` on one
    line, without Python's file:line prefix; another package's warning keeps Python's format."""
    code = ("import sys, warnings\n"
            "from cfrace.cli import main as m\n"
            "warnings.formatwarning = m.format_warning\n"
            "from cfrace.sim.simulator import Simulator\n"
            "from cfrace.track import load_track\n"
            "from cfrace.drone import load_profile\n"
            "Simulator(load_track('lemniscate'), load_profile('cf2x_paper'), 1, 17, obstacles=False)\n"
            "warnings.warn_explicit('other', UserWarning, '/elsewhere/pkg.py', 7)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 0, out.stderr
    assert lines[0].startswith("warning: simulator: 17 drones per world"), lines
    assert "RuntimeWarning" not in out.stderr and "race_env.py" not in lines[0]
    assert "/elsewhere/pkg.py:7: UserWarning: other" in out.stderr


def test_main_installs_the_one_line_warning_format():
    import warnings

    from cfrace.cli import main as m

    before = warnings.formatwarning
    try:
        with pytest.raises(SystemExit):
            main(["--version"])
        assert warnings.formatwarning is m.format_warning
    finally:
        warnings.formatwarning = before
