"""Sweep files: validation, names, dependency order, the exact `cfrace train` argument lists, and the
local sequential executor on a real tiny run (start, interrupt, resume)."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from cfrace.errors import ConfigError
from cfrace.sweep.parse import load_spec, parse_spec
from cfrace.sweep.spec import train_options


def spec(body: str, tmp_path: Path, name: str = "s.yaml"):
    """Load BASE + the (indented) body from a file."""
    p = tmp_path / name
    p.write_text(BASE + textwrap.dedent(body))
    return load_spec(p)


DS_FILE = Path(__file__).resolve().parents[1] / "policies" / "ds_lemniscate.onnx"
BASE = """
version: 1
out: runs/x
defaults: {preset: cpu, threads: 1, track: lemniscate}
"""


def test_grid_and_runs_in_dependency_order(tmp_path):
    sw = spec("""
    runs:
      - name: ours
        method: ours
        init_from: dm
        init_critic: true
        fixed_opponent: ds_s0
        set: {lr: 5.0e-5, bound_coef: 0, actor_hidden: [16, 16], value_clip: null}
        export: {file: policies/x.onnx}
        select: {races: 50}
      - name: dm
        method: dm
        init_from: ds_s1
        after: [ss_s0]
        obstacles: false
        random_phase: true
        minutes: 30
        steps: 1000
    grid:
      name: "{method}_s{seed}"
      method: [ds, ss]
      seed: [0, 1]
      minutes: 0.2
    """, tmp_path)
    names = [r.name for r in sw.runs]
    assert set(names) == {"ds_s0", "ds_s1", "ss_s0", "ss_s1", "dm", "ours"}
    for r in sw.runs:  # every run after its dependencies
        for d in r.deps:
            assert names.index(d) < names.index(r.name)
    ours = sw.run("ours")
    assert ours.deps == ("dm", "ds_s0") and ours.select == {"races": 50}
    assert ours.export == {"file": "policies/x.onnx", "agent": "best"}
    argv = ours.train_argv("R")
    assert argv[0] == "train" and argv[-2:] == ["--out", "R/ours"]
    assert argv[argv.index("--init-from") + 1] == "R/dm/checkpoint.pt"
    assert argv[argv.index("--fixed-opponent") + 1] == "R/ds_s0/checkpoint.pt"
    assert "--init-critic" in argv and "--random-phase" not in argv
    sets = [argv[i + 1] for i, a in enumerate(argv) if a == "--set"]
    assert sets == ["lr=5e-05", "bound_coef=0", "actor_hidden=[16, 16]", "value_clip=none"]
    dm = sw.run("dm").train_argv("R")
    assert "--no-obstacles" in dm and "--random-phase" in dm and dm[dm.index("--steps") + 1] == "1000"
    assert ours.export_argv("R") == ["export", "R/ours/checkpoint.pt", "-o", "policies/x.onnx", "--agent", "best"]
    assert sw.run("ds_s1").train_argv("R") == ["train", "--preset", "cpu", "--threads", "1", "--track", "lemniscate",
                                               "--minutes", "0.2", "--method", "ds", "--seed", "1",
                                               "--out", "R/ds_s1"]
    groups = {label: [r.name for r in runs] for label, runs in sw.groups().items()}
    assert sorted(groups.values()) == [["dm"], ["ds_s0", "ds_s1"], ["ours"], ["ss_s0", "ss_s1"]]


def test_argv_is_accepted_by_the_train_command(tmp_path):
    """Every option the spec writes is parsed by the real `cfrace train` (typer), no unknown flag."""
    import typer
    from typer.testing import CliRunner

    from cfrace.cli.train import train_cmd

    import functools

    seen = {}
    app = typer.Typer()

    @functools.wraps(train_cmd)  # the real command's options, without training
    def capture(*a, **kw):
        seen.update(kw)

    app.command()(capture)
    sw = spec("""
    runs:
      - {name: a, method: ds, seed: 3, steps: 100, random_phase: true, obstacles: true, episode_s: 20,
         set: {epochs: 2}, checkpoint_min: 0.5, critic_warmup: 3, critic_warmup_lr: 0.001, flight_obs: true,
         envs: 8, profile: cf2x_paper, device: cpu}
    """, tmp_path)
    res = CliRunner().invoke(app, sw.run("a").train_argv("R")[1:])
    assert res.exit_code == 0, res.output
    assert seen["seed"] == 3 and seen["random_phase"] and seen["obstacles"] and seen["set_"] == ["epochs=2"]
    assert seen["out"] == Path("R/a") and seen["envs"] == 8 and seen["flight_obs"]


def test_reward_weights_become_reward_flags(tmp_path):
    sw = spec("""
    runs:
      - {name: a, method: ss, reward: {crash: 20, contact: 1}, set: {lr: 2.0e-5}}
    """, tmp_path)
    argv = sw.run("a").train_argv("R")
    assert [argv[i + 1] for i, a in enumerate(argv) if a == "--reward"] == ["crash=20", "contact=1"]
    assert [argv[i + 1] for i, a in enumerate(argv) if a == "--set"] == ["lr=2e-05"]


@pytest.mark.parametrize("body, message", [
    ("runs: [{name: a, method: ds, colour: red}]", "runs[0].colour: unknown key"),
    ("runs: [{name: a, method: ds}, {name: a, method: ss}]", "duplicate run name 'a'"),
    ("runs: [{name: a, method: ds, init_from: nothere}]", "runs[0].init_from: 'nothere' is neither a run"),
    ("runs: [{name: a, method: ds, after: [b]}]", "runs[0].after: unknown run 'b'"),
    (f"runs: [{{name: a, method: ours, fixed_opponent: '{DS_FILE},nothere.onnx'}}]",
     "runs[0].fixed_opponent: 'nothere.onnx' is neither a run"),
    ("runs: [{name: a, method: ds, after: [b]}, {name: b, method: ds, init_from: a}]",
     "dependency cycle: a -> b -> a"),
    ("runs: [{name: a, method: ds, init_from: a}]", "refers to itself"),
    ("runs: [{name: a, method: ds, seed: x}]", "runs[0].seed: expected an integer"),
    ("runs: [{name: a, method: ds, random_phase: 1}]", "runs[0].random_phase: expected true or false"),
    ("runs: [{name: a, method: ds, set: {lrr: 1}}]", "--set 'lrr=1'"),
    ("runs: [{name: a, method: ss, reward: {crashh: 20}}]", "runs[0].reward: --reward crashh: unknown reward weight"),
    ("runs: [{name: a, method: ss, reward: 20}]", "runs[0].reward: expected a mapping of --reward items"),
    ("runs: [{name: a, method: ds, out: x}]", "runs[0].out: set by the sweep"),
    ("runs: [{name: a, method: ds, export: {file: a.pt}}]", "export.file: expected an .onnx path"),
    ("runs: [{name: a, method: ds, export: {file: a.onnx, agent: me}}]", "export.agent"),
    ("runs: [{method: ds}]", "runs[0].name: missing"),
    ("grid: {name: '{method}_{colour}', method: [ds]}", "'{colour}' is not an option"),
    ("grid: {method: [ds], seed: []}", "grid.seed: empty list"),
    ("grid: {method: [ds, 3]}", "grid.method: expected a string"),
    ("colours: 3", "colours: unknown key"),
    ("", "no runs"),
    ("runs: [{name: a, method: dss}]", "runs[0] (a).method: unknown method 'dss' (choose from ours, ds, ss, dm)"),
    ("grid: {method: [ds, ss], track: lemniscat}", "grid (ds_lemniscat_s0).track: "),
    ("runs: [{name: a, method: ds, track: tracks/nothere.yaml}]", "runs[0] (a).track: tracks/nothere.yaml: no such"),
])
def test_bad_files_give_one_line(tmp_path, body, message):
    with pytest.raises(ConfigError) as exc:
        spec(body, tmp_path)
    text = str(exc.value)
    assert message in text and "\n" not in text and "s.yaml" in text


def test_a_track_file_is_a_track(tmp_path):
    track = Path(__file__).resolve().parents[1] / "tracks" / "complex.yaml"
    (run,) = spec(f"runs: [{{name: a, method: ss, track: {track}}}]", tmp_path).runs
    assert run.options["track"] == str(track)
    with pytest.raises(ConfigError, match=r"runs\[0\] \(a\)\.track: .*lemniscat.yaml: no such track file \(known: "):
        spec("runs: [{name: a, method: ss, track: lemniscat}]", tmp_path)


def test_version_and_out_required(tmp_path):
    with pytest.raises(ConfigError, match="version: expected 1"):
        parse_spec({"out": "x", "runs": [{"name": "a", "method": "ds", "track": "t"}]})
    with pytest.raises(ConfigError, match=r"out: expected the output folder \(a string; or give --out\), got None"):
        parse_spec({"version": 1, "runs": [{"name": "a", "method": "ds", "track": "t"}]})
    with pytest.raises(ConfigError, match="track missing"):
        parse_spec({"version": 1, "out": "x", "runs": [{"name": "a", "method": "ds"}]})


def test_default_name_and_existing_path_reference(tmp_path):
    ck = tmp_path / "src"
    ck.mkdir()
    sw = spec(f"""
    grid: {{method: [ds], seed: [4], obstacles: true, init_from: {ck}}}
    """, tmp_path)
    (run,) = sw.runs
    assert run.name == "ds_lemniscate_obstacles_s4" and run.deps == ()
    assert run.train_argv("R")[run.train_argv("R").index("--init-from") + 1] == str(ck)


def test_options_follow_the_train_command():
    opts = train_options()
    assert opts["obstacles"].kind == "toggle" and opts["random_phase"].kind == "flag"
    assert opts["set"].kind == "set" and opts["minutes"].type is float and opts["seed"].type is int
    assert "out" not in opts and "resume" not in opts and opts["keep_checkpoints"].kind == "flag"


TINY = """
version: 1
out: {out}
defaults: {{track: lemniscate, threads: 1, envs: 32, checkpoint_min: 0.01,
           set: {{actor_hidden: [16], critic_hidden: [16]}}}}
runs:
  - {{name: b, method: ds, steps: 1500, init_from: a, init_critic: true, critic_warmup: 1,
     export: {{file: {out}/b.onnx}}}}
  - {{name: a, method: ds, seed: 1, steps: 1500}}
"""


def test_run_local_resumes_and_chains(tmp_path):
    """Real `cfrace train` processes: a run stopped early is resumed for the rest of its steps, a
    warm start follows its source, the export lands, and a second call only calls the hook."""
    import subprocess

    from cfrace.sweep.local import cfrace_argv, run_local
    from cfrace.sweep.spec import checkpoint_progress

    p = tmp_path / "s.yaml"
    p.write_text(TINY.format(out=tmp_path / "out"))
    sw = load_spec(p)
    assert [r.name for r in sw.runs] == ["a", "b"]
    a, b = sw.runs
    # an interrupted run: `a` trained for one iteration (768 env steps) of its 1500
    argv = a.train_argv(sw.out)
    argv[argv.index("--steps") + 1] = "700"
    subprocess.run(cfrace_argv(argv), check=True, capture_output=True)
    assert a.started(sw.out) and not a.trained(sw.out)
    resume = a.resume_argv(sw.out)
    assert resume[:3] == ["train", "--resume", str(tmp_path / "out" / "a")] and "--method" not in resume
    calls = []
    reports = run_local(sw, post_run=lambda run, d: calls.append((run.name, d.name)), echo=lambda s: None,
                        log_dir=True)
    assert [(r["name"], r["action"], r["error"]) for r in reports] == [("a", "resume", None), ("b", "start", None)]
    assert checkpoint_progress(a.checkpoint(sw.out))[0] == 1536       # 2 iterations: resumed, not restarted
    assert "resumed" in (tmp_path / "out" / "a" / "train.log").read_text()
    assert b.done(sw.out) and (tmp_path / "out" / "b.onnx").exists()
    assert calls == [("a", "a"), ("b", "b")]
    assert run_local(sw, post_run=lambda run, d: calls.append(run.name), echo=lambda s: None) == []
    assert calls[-2:] == ["a", "b"]


def test_dry_run_prints_commands_and_state(tmp_path):
    from typer.testing import CliRunner

    from cfrace.cli.main import app

    p = tmp_path / "s.yaml"
    p.write_text(TINY.format(out=tmp_path / "out"))
    res = CliRunner().invoke(app, ["sweep", str(p), "--dry-run"], env={"COLUMNS": "400"})
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert lines[0] == "a (new; after nothing)" and lines[2] == "b (new; after a)"
    assert lines[1].startswith("  cfrace train --track lemniscate") and lines[1].endswith(f"--out {tmp_path}/out/a")
    assert lines[4] == f"  cfrace export {tmp_path}/out/b/checkpoint.pt -o {tmp_path}/out/b.onnx --agent best"
    assert not (tmp_path / "out").exists()


def _cfrace(capsys, *args) -> tuple[int, str, str]:
    """`cfrace ARGS` in this process: (exit code, stdout, stderr)."""
    from cfrace.cli.main import main

    with pytest.raises(SystemExit) as exc:
        main(list(args))
    out, err = capsys.readouterr()
    return exc.value.code, out, err


@pytest.mark.parametrize("body, message", [
    ("runs: [{name: a, method: ds}, {name: b, method: ss}, {name: c, method: ss, init_from: dz}]",
     "runs[2].init_from: 'dz' is neither a run of this sweep nor an existing checkpoint or run folder"),
    ("runs: [{name: a, method: dss}]", "runs[0] (a).method: unknown method 'dss'"),
    ("runs: [{name: a, method: ds, track: lemniscat}]", "runs[0] (a).track: "),
])
def test_dry_run_refuses_what_the_run_refuses(tmp_path, capsys, body, message):
    p = tmp_path / "s.yaml"
    p.write_text(BASE + body)
    for mode in ("--dry-run", "--sequential"):
        code, out, err = _cfrace(capsys, "sweep", str(p), mode)
        assert code == 2 and out == "", (mode, out)
        assert err.startswith(f"error: {p}: {message}") and err.count("\n") == 1, (mode, err)


def test_dry_run_prints_what_would_run(tmp_path, capsys):
    """Per state: a fresh start, a resume for the rest of the budget, an export only, nothing."""
    import torch

    from cfrace.rl.checkpoint import FORMAT

    out = tmp_path / "out"
    p = tmp_path / "s.yaml"
    p.write_text(BASE.replace("runs/x", str(out)) + f"""
runs:
  - {{name: fresh, method: ds, steps: 5000}}
  - {{name: stopped, method: ds, minutes: 1}}
  - {{name: trained, method: ds, steps: 500, export: {{file: {tmp_path}/t.onnx}}}}
  - {{name: finished, method: ds, steps: 500}}
""")
    for name, wall_s in (("stopped", 6.0), ("trained", 9.0), ("finished", 9.0)):
        (out / name).mkdir(parents=True)
        torch.save({"format": FORMAT, "runner": {"env_steps": 768}, "wall_s": wall_s}, out / name / "checkpoint.pt")
    code, text, err = _cfrace(capsys, "sweep", str(p), "--dry-run")
    assert code == 0, err
    assert text.splitlines() == [
        "fresh (new; after nothing)",
        f"  cfrace train --preset cpu --threads 1 --track lemniscate --method ds --steps 5000 --out {out}/fresh",
        "stopped (interrupted; after nothing)",
        f"  cfrace train --resume {out}/stopped --threads 1 --minutes 0.9",
        "trained (trained, not exported; after nothing)",
        f"  cfrace export {out}/trained/checkpoint.pt -o {tmp_path}/t.onnx --agent best",
        "finished (done; after nothing)"]


def test_out_option_stands_in_for_a_missing_out_key(tmp_path, capsys):
    p = tmp_path / "nomethod.yaml"
    p.write_text("version: 1\nruns: [{name: a, method: ds, track: lemniscate, steps: 1}]\n")
    assert load_spec(p, out=tmp_path / "t").out == str(tmp_path / "t")
    code, text, err = _cfrace(capsys, "sweep", str(p), "--out", str(tmp_path / "t"), "--dry-run")
    assert code == 0, err
    assert text.splitlines()[1].endswith(f"--steps 1 --out {tmp_path}/t/a")
    code, _, err = _cfrace(capsys, "sweep", str(p), "--dry-run")
    assert code == 2 and err == f"error: {p}: out: expected the output folder (a string; or give --out), got None\n"
    p.write_text("version: 1\nout: 3\nruns: [{name: a, method: ds, track: lemniscate, steps: 1}]\n")
    with pytest.raises(ConfigError, match="out: expected the output folder"):   # a bad one stays an error
        load_spec(p, out=tmp_path / "t")
    p.write_text(f"version: 1\nout: {tmp_path}/file_out\nruns: [{{name: a, method: ds, track: lemniscate}}]\n")
    assert load_spec(p, out=tmp_path / "t").out == str(tmp_path / "t") and load_spec(p).out == f"{tmp_path}/file_out"
