"""cfrace.evaluate.race.race_crashes (benchmarks/race_crashes.py prints it): every crash of the ego in real rollouts of shipped policies, as `cfrace race` counts them."""

from cfrace.evaluate.race import race, race_crashes
from cfrace.sim.simulator import REASONS


def test_crashes_match_the_race_and_name_the_opponent():
    rows = race_crashes("ours", "ds", "complex", True, 6, 0)
    r = race("complex", "ours", "ds", obstacles=True, races=6, seed=0)
    assert len(rows) == r.ego_stats["crashes"] > 0          # the same races: the same crashes
    assert r.recording.pos.shape[1] == 0                    # positions only with record_all (or plots)
    for row in rows:
        assert row["reason"] in REASONS.values() and row["reason"] != "none"
        assert 0.0 < row["t_s"] <= 45.0 and row["opp_dist_m"] >= 0.0
    assert any(row["opp_racing"] and row["opp_dist_m"] < 1.5 for row in rows)   # this setting: contacts with DS

