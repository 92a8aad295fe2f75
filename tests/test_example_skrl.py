"""benchmarks/train_skrl_ppo.py runs: skrl's PPO (a third-party trainer) trains on RaceVectorEnv,
logs to TensorBoard and evaluates the mean action (a few seconds of training)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("skrl")
pytest.importorskip("gymnasium")

EXAMPLE = Path(__file__).resolve().parents[1] / "benchmarks" / "train_skrl_ppo.py"


@pytest.mark.timeout(180)
def test_skrl_example_trains(tmp_path):
    res = subprocess.run([sys.executable, str(EXAMPLE), "--minutes", "0.05", "--worlds", "16", "--rollouts", "8",
                          "--out", str(tmp_path / "skrl")], capture_output=True, text=True, timeout=170,
                         cwd=tmp_path)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    lines = res.stdout.splitlines()
    assert any(line.startswith("trained ") and "env steps" in line for line in lines), res.stdout
    assert any(line.startswith("mean action, 64 races") and "->" in line for line in lines), res.stdout
    assert list((tmp_path / "skrl").rglob("events.out.tfevents.*")), "no TensorBoard log written"
