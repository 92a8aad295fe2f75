"""Race progress for the flight loop: cfrace.sim.gates.RaceProgress with a numpy update.

The rule is the simulator's (cfrace.sim.gates.crossing, to_gate_frame; same constants, float64),
re-written with numpy on the two drones because the torch version costs ~0.1-0.3 ms per call on
(2, 3) tensors, a third of the loop's compute budget. tests/test_flight_core.py proves the two
give the same passes, frame hits, targets, laps and lap times on random and flown trajectories.
The gate yaw cos/sin are computed once by torch so both paths use the very same values.
"""

from __future__ import annotations

import numpy as np
import torch

from cfrace.sim.gates import FRAME_HIT_HALF, PASS_HALF, PASS_RADIUS, RaceProgress


class FastRaceProgress(RaceProgress):
    """Same state and results as RaceProgress; update() in numpy."""

    def __post_init__(self):
        super().__post_init__()
        yaw = torch.as_tensor(np.asarray(self.gates)[:, 3], dtype=torch.float64)
        self._cos = torch.cos(yaw).numpy()   # (G,)
        self._sin = torch.sin(yaw).numpy()
        self._centre = np.asarray(self.gates, dtype=np.float64)[:, :3]   # (G, 3)

    def _local(self, pos: np.ndarray, tgt: np.ndarray) -> np.ndarray:
        d = pos - self._centre[tgt]
        c, s = self._cos[tgt], self._sin[tgt]
        return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=-1)

    def update(self, t: float, positions: np.ndarray):
        """Returns (passed, lap_done, frame_hit) bool arrays (N,) for this tick."""
        pos = np.array(positions, dtype=np.float64)
        if np.isnan(self._lap_start).all():
            self._lap_start[:] = t
        prev = pos.copy() if self._prev is None else np.asarray(self._prev, dtype=np.float64)
        tgt = self.target
        local, prev_local = self._local(pos, tgt), self._local(prev, tgt)
        crossed = (prev_local[:, 0] > 0.0) & (local[:, 0] <= 0.0)
        frac = prev_local[:, 0] / np.maximum(prev_local[:, 0] - local[:, 0], 1e-9)
        yz = prev_local[:, 1:] + frac[:, None] * (local[:, 1:] - prev_local[:, 1:])
        ay, az = np.abs(yz[:, 0]), np.abs(yz[:, 1])
        near = np.sqrt((local * local).sum(-1)) < PASS_RADIUS
        passed = crossed & near & (ay < PASS_HALF) & (az < PASS_HALF)
        hit = crossed & (ay < self.outer_half) & (az < self.outer_half) & ((ay >= FRAME_HIT_HALF) | (az >= FRAME_HIT_HALF))
        self._prev = pos
        g = len(self.gates)
        self.gates_passed += passed
        self.target = np.where(passed, (self.target + 1) % g, self.target)
        lap_done = passed & (self.gates_passed % g == 0)
        for i in np.flatnonzero(lap_done):
            self.lap_times[i].append(float(t - self._lap_start[i]))
            self._lap_start[i] = t
        self.laps += lap_done
        self.frame_hits += hit
        return passed, lap_done, hit
