"""benchmarks/landing_ticks.py: the CPU of each landing tick of `cfrace bench loop`."""

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_the_landing_ticks_of_a_four_drone_bench_are_reported(tmp_path):
    out = tmp_path / "ticks.json"
    subprocess.run([sys.executable, str(REPO / "benchmarks" / "landing_ticks.py"), "--drones", "4", "--track", "complex",
                    "--duration-s", "1", "--json", str(out)], check=True, cwd=REPO, capture_output=True, timeout=240)
    doc = json.loads(out.read_text())
    ticks = {k: n for _, k, n in doc["landing_ticks_cpu_ms"]}
    first = min(ticks)
    assert ticks[first] == 4 and len(ticks) > 10 and doc["racing_cpu_ms"]["p50"] > 0.0
    assert doc["cfrace"].startswith(str(REPO))
