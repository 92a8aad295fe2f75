"""The paper's published figures that `cfrace reproduce` sets beside its own.

Source: the paper "Agile Flight Emerges from Multi-Agent Competitive Racing": Table I (single-agent
tests, 50 runs of 3 laps), Sec. IV-B (head-to-head, 50 races of 3 laps: the full matrices are only
in a figure; the text gives the cells below and ours' average), Sec. IV-E (self-play on the complex
track) and Sec. IV-C (sim-to-real speed gap). docs/evaluation.md lists them too.
"""

from __future__ import annotations

SETTINGS = (("lemniscate", False), ("lemniscate", True), ("complex", False), ("complex", True))
SCHEMES = ("ds", "ss", "dm", "ours")


def setting_name(track: str, obstacles: bool) -> str:
    return f"{track}{' with obstacles' if obstacles else ''}"


#: Table I: (scheme, track, obstacles) -> (Avg. TTC s, Avg. speed m/s, collisions, success %); None = "--"
TABLE_I = {
    ("ds", "lemniscate", False): (4.76, 4.07, 0, 100),
    ("ds", "lemniscate", True): (None, None, 175, 0),
    ("ds", "complex", False): (5.68, 5.01, 1, 98),
    ("ds", "complex", True): (None, None, 0, 0),
    ("ss", "lemniscate", False): (5.29, 3.57, 0, 100),
    ("ss", "lemniscate", True): (5.72, 3.95, 12, 98),
    ("ss", "complex", False): (6.42, 4.30, 16, 94),
    ("ss", "complex", True): (10.08, 4.58, 69, 0),
}

#: head-to-head cells the paper's text states: (row, column, track, obstacles) -> row's win rate %
H2H = {
    ("ours", "ds", "lemniscate", False): 100.0,
    ("ours", "ds", "complex", False): 84.0,
    ("ours", "ss", "lemniscate", False): 62.0,
    ("ours", "dm", "lemniscate", False): 66.0,
}
#: ours' average win rate over its row, over all four settings (%)
OURS_AVERAGE_WIN = 91.17

#: self-play of ours on the complex track: max / mean speed and final-gate speed (m/s)
COMPETITION = {"vs_live_opponent": {"max": 9.9, "mean": 5.9, "final_gate": 8.3},
               "vs_crashed_opponent": {"max": 8.7, "mean": 5.3, "final_gate": 5.4}}

#: sim-to-real: average-speed gap (m/s) between simulation and the real drones; in simulation both
#: failure and collision rates were zero
TRANSFER_SPEED_GAP = {"ds": 0.76, "ours": 0.43}
