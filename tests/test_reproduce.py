"""`cfrace reproduce --quick` on the shipped policies, and the paper's reference figures it prints."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from cfrace.cli.main import app
from cfrace.reproduction import paper
from cfrace.reproduction.report import claims, markdown
from cfrace.reproduction.evidence import shipped


def test_paper_reference_figures():
    """The figures the report sets beside its own, as the paper prints them (Table I, Sec. IV)."""
    assert len(paper.TABLE_I) == 8
    assert paper.TABLE_I[("ds", "lemniscate", False)] == (4.76, 4.07, 0, 100)
    assert paper.TABLE_I[("ds", "complex", True)] == (None, None, 0, 0)
    assert paper.TABLE_I[("ss", "lemniscate", True)] == (5.72, 3.95, 12, 98)
    assert paper.TABLE_I[("ss", "complex", True)] == (10.08, 4.58, 69, 0)
    assert paper.H2H[("ours", "ds", "lemniscate", False)] == 100.0 and paper.H2H[("ours", "ds", "complex", False)] == 84.0
    assert paper.OURS_AVERAGE_WIN == 91.17
    assert paper.COMPETITION["vs_live_opponent"] == {"max": 9.9, "mean": 5.9, "final_gate": 8.3}
    assert paper.COMPETITION["vs_crashed_opponent"] == {"max": 8.7, "mean": 5.3, "final_gate": 5.4}


def test_reproduce_quick_on_the_shipped_policies(tmp_path):
    out = tmp_path / "rep"
    r = CliRunner().invoke(app, ["reproduce", "--quick", "--out", str(out)])
    assert r.exit_code == 0, r.output
    rep = json.loads((out / "report.json").read_text())
    md = (out / "report.md").read_text()
    # all 8 of the paper's Table I rows are in the report, measured where a policy is shipped
    paper_rows = [row for row in rep["table_i"] if row["paper"] is not None]
    assert len(paper_rows) == 8
    assert "| lemniscate | ds |" in md and "4.76, 4.07, 0, 100 %" in md and "10.08, 4.58, 69, 0 %" in md
    lem = [row for row in rep["table_i"] if row["setting"] == "lemniscate"]
    assert {row["scheme"] for row in lem} == set(shipped("lemniscate", False))
    assert all(0.0 <= row["success"] <= 1.0 for row in lem)
    # every setting with two or more shipped schemes has a matrix and its heatmap on disk
    for name, sec in rep["settings"].items():
        if len(sec["schemes"]) >= 2:
            assert (out / sec["matrix"]["heatmap"]).stat().st_size > 1000
            assert f"### {name}" in md
    assert any(c["claim"].startswith("ours beats DS on the lemniscate") for c in rep["claims"])
    assert "ours beats DS on the lemniscate" in r.output
    # the transfer comparison ran lockstep dry-runs through the flight stack on the other profile
    lem = [t for t in rep["transfer"] if t["track"] == "lemniscate"]
    assert {t["policy"] for t in lem} == {"ours", "ds"} and all(t["profile_flown"] == "cf21bl" for t in lem)
    assert all(t["stack_speed_mps"] and t["sim_speed_mps"] for t in lem) and "## Transfer through the flight stack" in md
    # the robustness grid at CI size: latencies 0 and 20 ms on both profiles, each policy alone and one duel
    rob = rep["robustness"]
    cells = {(c["latency_ms"], c["profile"]) for c in rob["cells"]}
    assert cells == {(lat, p) for lat in (0.0, 20.0) for p in ("cf2x_paper", "cf21bl")}
    assert all(set(c["alone"]) == {"ours", "ds"} and c["duel"]["races"] == 1 for c in rob["cells"])
    assert (out / rob["png"]).stat().st_size > 1000 and "## Robustness through the flight stack" in md


def test_claims_say_when_a_trend_does_not_hold():
    report = {"config": {"seed": 0}, "table_i": [
        {"setting": "lemniscate with obstacles", "scheme": "ds", "success": 0.9, "ttc_s": 5.0, "speed_mps": 4.0,
         "collisions": 1, "paper": None, "trend_holds": None},
        {"setting": "complex with obstacles", "scheme": "ds", "success": 0.0, "ttc_s": None, "speed_mps": None,
         "collisions": 3, "paper": None, "trend_holds": None}],
        "settings": {}, "competition": None}
    out = claims(report)
    dense = [c for c in out if c["claim"] == "the dense reward fails with obstacles (lemniscate, complex)"]
    assert dense and dense[0]["holds"] is False and dense[0]["measured"] == "90%, 0%"
    md = markdown({**report, "commit": "x", "date": "d", "wall_s": 1.0, "missing": {}, "curves": [], "claims": out,
                   "config": {"quick": True, "runs": 1, "laps": 1, "races": 1, "seed": 0, "test_seeds": [1]}})
    assert "**no**" in md
