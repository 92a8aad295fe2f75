"""`cfrace tournament --ray` equals the local tournament cell for cell (same seed): the shipped
policies, the pairs spread over a real local Ray instance, every figure of the JSON compared."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

pytest.importorskip("ray")

from cfrace.cli.main import app  # noqa: E402
from cfrace.evaluate.race import tournament  # noqa: E402
from cfrace.evaluate.ray_tournament import split  # noqa: E402


def test_split_keeps_order_and_balance():
    assert split(list(range(7)), 3) == [[0, 1, 2], [3, 4], [5, 6]]
    assert split([1, 2], 5) == [[1], [2]]
    assert sum(split(list(range(6)), 2), []) == list(range(6))


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_ray_tournament_equals_local(tmp_path):
    import ray

    policies = ["ours", "ds", "ss", "dm"]
    local = tournament(policies, "lemniscate", races=6, laps=1, seed=3).to_json()
    out = tmp_path / "ray.json"
    try:
        res = CliRunner().invoke(app, ["tournament", *policies, "--track", "lemniscate", "--races", "6", "--laps", "1",
                                       "--seed", "3", "--ray", "--json", str(out)])
        assert res.exit_code == 0, res.output
        assert ray.is_initialized() and ray.cluster_resources()["CPU"] >= 2   # pairs split over >= 2 tasks
    finally:
        ray.shutdown()
    remote = json.loads(out.read_text())
    local = json.loads(json.dumps(local))   # same float rendering
    local.pop("wall_s"), remote.pop("wall_s")
    assert remote == local
    assert len(remote["pairs"]) == 6 and {p["ego"] for p in remote["pairs"]} == {"ours", "ds", "ss"}
    # not a degenerate tournament: somebody wins somewhere
    assert any(v for row in remote["win_rate"] for v in row if v is not None)
