"""cfrace.rl.curves.training_figures (benchmarks/scratch_progress.py tabulates it): the training figures read from a run's metrics.csv."""

from pathlib import Path

from cfrace.rl.curves import near, training_figures


def _csv(path: Path, header: list[str], rows: list[list]) -> None:
    path.write_text("\n".join([",".join(header)] + [",".join(str(v) for v in r) for r in rows]) + "\n")


BASE = ["iteration", "env_steps", "wall_s", "stat_gates_per_s", "stat_success", "std_agent0"]


def test_single_agent_rows_keep_their_std(tmp_path):
    _csv(tmp_path / "metrics.csv", BASE, [[1, 100, 2.0, 0.5, 0.1, 0.8], [2, 200, 4.0, 0.6, 0.2, 0.7]])
    rows = training_figures(tmp_path)
    assert [r["iteration"] for r in rows] == [1.0, 2.0]
    assert [r["std1"] for r in rows] == [0.8, 0.7]      # no agent 1: agent 0's std


def test_two_agent_rows_carry_agent_one_std(tmp_path):
    _csv(tmp_path / "metrics.csv", BASE + ["std_agent1"], [[1, 100, 2.0, 0.5, 0.1, 0.8, 0.3]])
    rows = training_figures(tmp_path)
    assert rows[0]["std"] == 0.8 and rows[0]["std1"] == 0.3
    assert near(rows, 1, "std1") == 0.3
