"""`cfrace train` refuses every bad option before its banner (cfrace.rl.inputs.check_inputs): one
line, exit 2, no run folder; and its banner prints user-given text as given."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

import cfrace.rl.train as train_mod
from cfrace.rl.inputs import check_inputs
from cfrace.rl.train import TrainConfig

from test_rl_train import toy_factory

POLICIES = Path(__file__).resolve().parents[1] / "policies"


@pytest.fixture(autouse=True)
def _toy(monkeypatch):
    before = torch.get_num_threads()
    monkeypatch.setattr(train_mod, "make_env", toy_factory)   # a run that does start stays tiny
    yield
    torch.set_num_threads(before)


def _cfrace(monkeypatch, capsys, args) -> tuple[int, str, str]:
    from cfrace.cli.main import main

    monkeypatch.setattr(sys, "argv", ["cfrace", *args])
    with pytest.raises(SystemExit) as exc:
        main()
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


LATE = [  # each was refused only after the banner, the progress bar and the run folder
    (["--method", "ds", "--precision", "fp16"], "--precision 'fp16': choose from auto, fp32, bf16"),
    (["--method", "ds", "--fixed-opponent", f"{POLICIES}/ds_lemniscate.onnx"],
     "--fixed-opponent needs a multi-agent method (ours, dm), not ds"),
    (["--method", "ours", "--fixed-opponent", f"{POLICIES}/ds_lemniscate.onnx", "--fixed-opponent-frac", "1.5"],
     "--fixed-opponent-frac must be in (0, 1], got 1.5"),
    (["--method", "ours", "--drones", "4", "--fixed-opponent", f"{POLICIES}/ds_lemniscate.onnx",
      "--fixed-opponent-drones", "4"], "--fixed-opponent-drones 4: from 1 to 3 with 4 drones per world"),
    (["--method", "ours", "--init-from", f"{POLICIES}/ours_lemniscate.onnx", "--init-critic"],
     f"--init-critic: {POLICIES}/ours_lemniscate.onnx is an exported policy and has no critic"),
    (["--method", "ds", "--init-from", f"{POLICIES}/ours_lemniscate.onnx"],
     f"--init-from {POLICIES}/ours_lemniscate.onnx: layout race42 does not fit into solo36"),
    # a frozen opponent races as it was trained: on this track, with this obstacles setting
    (["--method", "ours", "--fixed-opponent", f"{POLICIES}/ds_complex.onnx"],
     f"--fixed-opponent {POLICIES}/ds_complex.onnx: trained on track 'complex', not 'lemniscate'"),
    (["--method", "ours", "--obstacles", "--fixed-opponent", f"{POLICIES}/ds_lemniscate.onnx"],
     f"--fixed-opponent {POLICIES}/ds_lemniscate.onnx: trained without obstacles, but the race is with obstacles"),
]


@pytest.mark.parametrize("args, message", LATE)
def test_refused_before_the_banner(tmp_path, monkeypatch, capsys, args, message):
    out = tmp_path / "run"
    code, text, err = _cfrace(monkeypatch, capsys, ["train", "--track", "lemniscate", "--steps", "10",
                                                    "--out", str(out), *args])
    assert code == 2 and text == "" and not out.exists(), (text, err)
    assert err.startswith(f"error: {message}") and err.count("\n") == 1, err


def test_a_fitting_frozen_opponent_and_warm_start_pass():
    cfg = TrainConfig("ours", "lemniscate", fixed_opponent=f"{POLICIES}/ds_lemniscate.onnx",
                      init_from=f"{POLICIES}/ds_lemniscate.onnx", drones=4, fixed_opponent_drones=3)
    assert check_inputs(cfg)[0].name == "lemniscate"
    # a policy without obstacles still warm-starts a run with them (docs/training.md, warm start)
    check_inputs(TrainConfig("ours", "lemniscate", obstacles=True, init_from=f"{POLICIES}/ds_lemniscate.onnx"))


def test_the_banner_prints_paths_as_given(tmp_path):
    """No emoji codes (a:abc:b is not a🔤b), no markup ([b] stays)."""
    from typer.testing import CliRunner

    from cfrace.cli.main import app

    out = tmp_path / "a:abc:b[b]x"
    res = CliRunner().invoke(app, ["train", "--method", "ours", "--track", "complex", "--envs", "16", "--steps", "256",
                                   "--device", "cpu", "--out", str(out)])
    assert res.exit_code == 0, res.output
    text = res.output.replace("\n", "")
    assert f"{out}/checkpoint.pt" in text and f"{out}/training_curve.png" in text, res.output
    assert text.count(str(out)) >= 4 and "\U0001f524" not in text, res.output    # the banner's too
