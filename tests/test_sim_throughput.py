"""`cfrace bench sim`: the start scenarios and one tiny real measurement (speed goals live in benchmarks)."""
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cfrace.sim.throughput import gates_start, hover_start, measure_sim
from cfrace.cli.main import app
from cfrace.track import load_track


@pytest.mark.parametrize("track", ["complex", "lemniscate"])
def test_gates_scenario_puts_every_drone_within_reach_of_a_gate(track):
    trk = load_track(track)
    pos = gates_start(trk, 13, 3).numpy()                       # (W, D, 3)
    g = trk.gate_array()
    reach = (trk.gate.opening / 2 + trk.gate.border) * math.sqrt(2)  # outer half-diagonal of a frame
    for w in range(13):
        gate = g[w % len(g)]
        d = np.linalg.norm(pos[w] - gate[:3], axis=-1)
        assert (d < reach).all() and (d > 0.5).all()
        n = np.array([math.cos(gate[3]), math.sin(gate[3]), 0.0])
        assert ((pos[w] - gate[:3]) @ n > 0.5).all()           # on the approach side
    hover = hover_start(trk, 13, 3).numpy()
    assert np.linalg.norm(hover[0] - g[0, :3], axis=-1).min() > reach


def test_measure_sim_gates_scenario_runs_the_real_kernel():
    r = measure_sim(4, 2, mode="eager", steps=2, warmup=1, substeps=2, track="complex", profile="cf2x_paper",
                    repeats=1, scenario="gates")
    assert r["scenario"] == "gates" and r["drone_steps_per_s"] > 0 and r["crashed_fraction"] == 0.0


def test_bench_sim_cli_json_and_bad_scenario(tmp_path):
    out = tmp_path / "b.json"
    res = CliRunner().invoke(app, ["bench", "sim", "--worlds", "2", "--modes", "eager", "--steps", "1", "--repeats", "1",
                                   "--no-peer", "--no-compile", "--scenario", "gates", "--json", str(out)])
    assert res.exit_code == 0, res.output
    assert json.loads(out.read_text())["results"][0]["scenario"] == "gates"
    bad = subprocess.run([str(Path(sys.executable).with_name("cfrace")), "bench", "sim", "--worlds", "2", "--modes", "eager",
                          "--no-peer", "--scenario", "nope"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and bad.stderr.strip() == "error: unknown scenario 'nope' (known: hover, gates)"
