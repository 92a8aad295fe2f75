"""The training pipeline file (policies/pipeline.yaml), `cfrace reproduce --train`, and choosing a
stage's checkpoint on validation runs (cfrace.reproduction.select / pipeline.post_stage)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cfrace.cli.main import app
from cfrace.errors import ConfigError
from cfrace.reproduction.pipeline import load_pipeline, post_stage
from cfrace.reproduction.select import choose
from cfrace.paths import POLICIES_DIR
from cfrace.rl.train import TrainConfig, train
from cfrace.sweep.parse import parse_spec


def test_every_shipped_policy_has_a_stage():
    sweep = load_pipeline()
    made = set()
    for run in sweep.runs:
        if run.export is not None:
            made.add(Path(run.export["file"]).name)
        if run.select is not None:
            made.add(Path(run.select["export"]).name)
    shipped = {p.name for p in POLICIES_DIR.glob("*.onnx")}
    assert shipped <= made, shipped - made
    assert len(made) == 16  # four schemes x four settings


def test_only_takes_the_dependencies_along():
    names = [r.name for r in load_pipeline(only="ours_complex").runs]
    assert names == ["ds_complex", "dm_complex", "ours_complex"]
    with pytest.raises(ConfigError, match="no stage matches"):
        load_pipeline(only="nothing*")


def test_reproduce_train_prints_the_commands(tmp_path):
    r = CliRunner().invoke(app, ["reproduce", "--train", "--only", "ss_lemniscate", "--runs-dir", str(tmp_path)])
    assert r.exit_code == 0, r.output
    assert "# 1. ds_lemniscate: to do" in r.output and "# 2. ss_lemniscate (after ds_lemniscate): to do" in r.output
    assert f"--init-from {tmp_path}/ds_lemniscate/checkpoint.pt --init-critic" in r.output.replace("\n", "")
    # options of the other mode are refused, not ignored (the report takes minutes)
    for args, says in ((["--run"], "--train --run"), (["--only", "ds_lemniscate"], "--train --only"),
                       (["--runs-dir", "x"], "--train --runs-dir"), (["--train", "--quick"], "not to --train"), (["--train", "--out", "x"], "not to --train")):
        bad = CliRunner().invoke(app, ["reproduce", *args])
        assert bad.exit_code != 0 and says in str(bad.exception), (args, bad.output)


def test_the_pipelines_repository_files_are_named_wherever_it_runs_from():
    """Stages warm-started from a shipped file name it absolutely (the printed commands run from any
    folder); references to other stages stay references."""
    from cfrace.paths import ROOT
    runs = {r.name: r for r in load_pipeline().runs}
    twin = next(r for r in runs.values() if str(r.options.get("init_from", "")).endswith("ours_lemniscate.onnx"))
    assert twin.options["init_from"] == str(ROOT / "policies" / "ours_lemniscate.onnx")
    assert all(Path(x).is_absolute() and Path(x).is_file() for x in twin.options["fixed_opponent"].split(","))
    assert runs["dm_lemniscate"].options["init_from"] == "ds_lemniscate"


def test_choose_rule():
    rows = [{"iteration": 1, "success": 0.9, "lap_time_s": 5.0}, {"iteration": 2, "success": 1.0, "lap_time_s": 6.0},
            {"iteration": 3, "success": 1.0, "lap_time_s": 5.5}, {"iteration": 4, "success": 1.0, "lap_time_s": 5.5}]
    assert choose(rows)["iteration"] == 3  # full success first, then the fastest lap, then the earliest
    races = [{"iteration": 1, "win_rate": 0.5}, {"iteration": 2, "win_rate": 0.8}, {"iteration": 3, "win_rate": 0.8}]
    assert choose(races)["iteration"] == 2


def test_choose_rule_with_a_least_success_alone():
    """select.alone_min: the highest win rate among the checkpoints that also fly alone that often;
    the plain highest win rate when none does."""
    races = [{"iteration": 1, "win_rate": 0.9, "success": 0.0}, {"iteration": 2, "win_rate": 0.7, "success": 0.92},
             {"iteration": 3, "win_rate": 0.8, "success": 0.9}, {"iteration": 4, "win_rate": 0.8, "success": 1.0}]
    assert choose(races)["iteration"] == 1
    assert choose(races, alone_min=0.9)["iteration"] == 3
    assert choose(races, alone_min=0.95)["iteration"] == 4
    assert choose(races, alone_min=1.01)["iteration"] == 1


def test_score_checkpoint_against_an_opponent_flies_it_alone_too(tmp_path, monkeypatch):
    """With alone=True a checkpoint is raced and flown alone (the flights stubbed: what is called with
    what, and what lands in the row)."""
    from types import SimpleNamespace

    import cfrace.evaluate.race as race_mod
    import cfrace.evaluate.single as single_mod
    import cfrace.export as export_mod
    import cfrace.rl.train as train_mod
    from cfrace.reproduction.select import score_checkpoint

    calls = []
    monkeypatch.setattr(export_mod, "export_checkpoint", lambda c, o, a: (o, {"train_steps": 7}, 0.0))
    monkeypatch.setattr(train_mod, "load_checkpoint", lambda c: {"wall_s": 60.0})
    alone_row = {"success_rate": 0.9, "lap_time_s": 5.5, "avg_speed_mps": 5.0, "collisions": 1, "laps_completed": 27,
                 "runs": 10}
    monkeypatch.setattr(single_mod, "evaluate", lambda *a: calls.append(("alone", a)) or SimpleNamespace(rows=[alone_row]))
    monkeypatch.setattr(race_mod, "race", lambda *a: calls.append(("race", a)) or SimpleNamespace(
        rates=lambda: {"ego_win_rate": 0.8, "opp_win_rate": 0.1}))
    ckpt = tmp_path / "it00042.pt"
    row = score_checkpoint(ckpt, "complex", False, "ds", 10, 3, 0, "ego", alone=True)
    assert [c[0] for c in calls] == ["alone", "race"]
    assert row["iteration"] == 42 and row["win_rate"] == 0.8 and row["success"] == 0.9 and row["laps_per_run"] == 2.7
    calls.clear()
    assert "success" not in score_checkpoint(ckpt, "complex", False, "ds", 10, 3, 0, "ego")
    assert [c[0] for c in calls] == ["race"]


def test_reproduce_train_says_the_least_success_alone(tmp_path):
    spec = tmp_path / "p.yaml"
    spec.write_text("version: 1\nout: runs/x\nruns:\n  - {name: a, method: ours, track: complex, steps: 1, select: "
                    "{against: ds, alone_min: 0.9, export: policies/x.onnx}}\n")
    from cfrace.reproduction.pipeline import describe

    text = "\n".join(describe(load_pipeline(spec), tmp_path))
    assert "races against ds among those finishing >= 90% of the runs alone" in text


def test_post_stage_scores_kept_checkpoints_and_exports_the_choice(tmp_path):
    """A one-iteration DS run with kept checkpoints; the stage flies each one and exports the chosen."""
    out_root = tmp_path / "runs"
    cfg = TrainConfig("ds", "lemniscate", False, num_envs=16, steps=1, out=str(out_root / "tiny"), device="cpu",
                      threads=1, seed=3, keep_checkpoints=True, precision="fp32",
                      overrides=(("actor_hidden", (16,)), ("critic_hidden", (16,)), ("epochs", 1)))
    train(cfg)
    assert (out_root / "tiny" / "checkpoints" / "it00001.pt").exists()
    spec = parse_spec({"version": 1, "out": str(out_root), "runs": [
        {"name": "tiny", "method": "ds", "track": "lemniscate", "seed": 3, "steps": 1,
         "select": {"runs": 2, "laps": 1, "seed": 0, "export": str(tmp_path / "chosen.onnx")}}]})
    run = spec.runs[0]
    said = []
    post_stage(run, out_root / "tiny", echo=said.append, curves_dir=tmp_path / "curves")
    assert (tmp_path / "chosen.onnx").stat().st_size > 1000
    sel = json.loads((out_root / "tiny" / "selected.json").read_text())
    assert sel["chosen"]["iteration"] == 1 and 0.0 <= sel["chosen"]["success"] <= 1.0
    with (out_root / "tiny" / "checkpoints" / "scores.csv").open() as fh:
        assert len(list(csv.DictReader(fh))) == 1
    curve = tmp_path / "curves" / "ds_lemniscate_s3.csv"
    assert curve.exists() and "env_steps" in curve.read_text().splitlines()[0]
    assert any("chose iteration 1" in s for s in said)
    # later stages naming this one start from the chosen checkpoint
    assert (out_root / "tiny" / "selected.pt").samefile(out_root / "tiny" / "checkpoints" / "it00001.pt")
    later = parse_spec({"version": 1, "out": str(out_root), "runs": [
        {"name": "tiny", "method": "ds", "track": "lemniscate", "steps": 1},
        {"name": "next", "method": "ss", "track": "lemniscate", "steps": 1, "init_from": "tiny"}]}).run("next")
    assert str(out_root / "tiny" / "selected.pt") in later.train_argv(out_root)


def test_a_stage_select_without_export_is_refused(tmp_path):
    bad = tmp_path / "p.yaml"
    bad.write_text("version: 1\nout: runs/x\nruns:\n  - {name: a, method: ds, track: lemniscate, select: {runs: 5}}\n")
    with pytest.raises(ConfigError, match="a.select"):
        load_pipeline(bad)


def test_a_warm_started_stage_chooses_only_among_its_own_actors():
    """Checkpoints taken during the critic warm-up hold the warm start's frozen actor: a stage that
    warm-starts chooses from iteration critic_warmup + 1 on (the pipeline's SS stage on the complex
    track had chosen its DS warm start at iteration 22 of a 40-iteration warm-up)."""
    from cfrace.reproduction.pipeline import first_own_iteration

    spec = parse_spec({"version": 1, "out": "runs", "runs": [
        {"name": "a", "method": "ds", "track": "complex", "steps": 1},
        {"name": "b", "method": "ss", "track": "complex", "steps": 1, "init_from": "a", "critic_warmup": 40},
        {"name": "c", "method": "ss", "track": "complex", "steps": 1, "init_from": "a"}]})
    assert first_own_iteration(spec.run("a").options) == 0
    assert first_own_iteration(spec.run("b").options) == 41
    assert first_own_iteration(spec.run("c").options) == TrainConfig.__dataclass_fields__["critic_warmup"].default + 1
    for run in load_pipeline().runs:   # every stage that warm-starts
        if run.options.get("init_from") and run.select is not None:
            assert first_own_iteration(run.options) > 1
