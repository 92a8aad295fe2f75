"""`cfrace train`, `cfrace export`, `cfrace bench train` through the real CLI entry (toy env)."""

from __future__ import annotations

import json
from pathlib import Path
import sys

import pytest
import torch
from typer.testing import CliRunner

import cfrace.rl.train as train_mod
from cfrace.rl.train import load_checkpoint
from cfrace.cli.main import app
from cfrace.policy import OnnxPolicy

from test_rl_train import toy_factory


@pytest.fixture(autouse=True)
def _toy(monkeypatch):
    before = torch.get_num_threads()
    monkeypatch.setattr(train_mod, "make_env", toy_factory)
    yield
    torch.set_num_threads(before)


def test_train_resume_export_cli(tmp_path):
    cli = CliRunner()
    out = tmp_path / "run"
    r = cli.invoke(app, ["train", "--method", "ours", "--track", "complex", "--envs", "16", "--steps", "512",
                         "--out", str(out), "--device", "cpu", "--seed", "3", "--checkpoint-min", "0.5"])
    assert r.exit_code == 0, r.output
    assert "done: 2 iterations" in r.output and "ego" in r.output and "adversary" in r.output
    assert (out / "training_curve.png").exists()
    r = cli.invoke(app, ["train", "--resume", str(out), "--steps", "768"])
    assert r.exit_code == 0, r.output
    assert "done: 3 iterations" in r.output
    # a resumed run keeps its own checkpoint interval unless --checkpoint-min is given again
    assert load_checkpoint(out / "checkpoint.pt")["train_config"]["checkpoint_every_s"] == 30.0
    r = cli.invoke(app, ["train", "--resume", str(out), "--steps", "1024", "--checkpoint-min", "2"])
    assert r.exit_code == 0, r.output
    assert load_checkpoint(out / "checkpoint.pt")["train_config"]["checkpoint_every_s"] == 120.0
    onnx_path = tmp_path / "p.onnx"
    r = cli.invoke(app, ["export", str(out / "checkpoint.pt"), "-o", str(onnx_path), "--agent", "adversary"])
    assert r.exit_code == 0, r.output
    assert "parity" in r.output
    pol = OnnxPolicy(onnx_path)
    assert pol.meta["agent"] == "adversary" and pol.meta["train_steps"] == 1024 and pol.meta["seed"] == 3


def test_bench_train_cli_json(tmp_path):
    js = tmp_path / "b.json"
    r = CliRunner().invoke(app, ["bench", "train", "--envs", "16", "--iterations", "1", "--device", "cpu",
                                 "--json", str(js)])
    assert r.exit_code == 0, r.output
    data = json.loads(js.read_text())
    assert data["env_steps_per_s"] > 0 and {"share_sim", "share_update", "share_inference"} <= set(data)


def test_cli_errors_are_one_line(tmp_path, monkeypatch, capsys):
    """Bad input through the CLI entry: exit code 2, one 'error:' line, no traceback."""
    from cfrace.cli.main import main

    cases = [["export", str(tmp_path / "missing.pt"), "-o", str(tmp_path / "x.onnx")],
             ["train", "--track", "complex", "--steps", "10"],
             ["train", "--resume", str(tmp_path / "nothing"), "--steps", "10"],
             ["train", "--method", "ours", "--track", "complex", "--steps", "10", "--device", "tpu"]]
    (tmp_path / "empty.pt").write_bytes(b"")
    run = ["--steps", "10", "--out", str(tmp_path / "new")]
    # refused before the banner and before the run folder is made (cfrace.rl.inputs.check_inputs)
    before_banner = [["train", "--method", "dss", "--track", "complex", *run],
                     ["train", "--method", "ds", "--track", "complexx", *run],
                     ["train", "--method", "ds", "--track", "complex", "--init-from", str(tmp_path / "empty.pt"), *run],
                     ["train", "--method", "ours", "--track", "complex", "--fixed-opponent",
                      f"{Path(__file__).parents[1] / 'policies' / 'ds_complex.onnx'},nope.onnx", *run],
                     ["export", str(tmp_path / "empty.pt"), "-o", str(tmp_path / "x.onnx")]]
    for args in cases + before_banner:
        monkeypatch.setattr(sys, "argv", ["cfrace", *args])
        with pytest.raises(SystemExit) as exc:
            main()
        assert exc.value.code == 2, args
        out = capsys.readouterr()
        err = out.err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: "), err
        if args in before_banner:
            assert "training" not in out.out and not (tmp_path / "new").exists(), (args, out.out)
