"""Race progress for the flight loop: cfrace.sim.gates.RaceProgress with a fast update on floats.

The rule is the simulator's (cfrace.sim.gates.crossing, to_gate_frame; its constants, float64),
repeated on plain Python floats per drone because array code costs several times more per call
on (2, 3) arrays (this one: ~20 us). tests/test_flight_core.py proves the two give the same
passes, frame hits, targets, laps and lap times on random and flown trajectories.
The gate yaw cos/sin are computed once by numpy, as in the reference, so both use the same values.
"""

from __future__ import annotations

import math

import numpy as np

from cfrace.sim.gates import FRAME_HIT_HALF, PASS_HALF, PASS_RADIUS, RaceProgress


class FastRaceProgress(RaceProgress):
    """Same state and results as RaceProgress; the gate crossings on Python floats."""

    def __post_init__(self):
        super().__post_init__()
        yaw = np.asarray(self.gates, dtype=np.float64)[:, 3]
        self._cos = np.cos(yaw)   # (G,)
        self._sin = np.sin(yaw)
        self._centre = np.asarray(self.gates, dtype=np.float64)[:, :3]   # (G, 3)
        # plain floats: for two drones Python arithmetic beats numpy's per-call overhead, and
        # float64 + - * / sqrt round exactly like numpy's float64 ops
        self._cos_l, self._sin_l = self._cos.tolist(), self._sin.tolist()
        self._centre_l = [tuple(c) for c in self._centre.tolist()]
        self._nothing = np.zeros(self.num_drones, bool)
        self._nothing.flags.writeable = False

    def update(self, t: float, positions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """RaceProgress.update. On the ticks where no drone crosses its target gate's plane (all but
        a few per lap) the bookkeeping is skipped: (passed, lap_done, hit) are then one read-only
        all-False array."""
        if np.isnan(self._lap_start[0]):
            self._lap_start[:] = t
        passed, hit = self._crossings(positions)
        if passed is None:
            return self._nothing, self._nothing, self._nothing
        return self._book(t, passed, hit)

    def peek(self, positions) -> None:
        """The crossing test of update() on these positions, changing nothing (the flight loop's
        warm-up runs it so that the tick's call finds its code and data in the caches)."""
        prev = self._prev
        try:
            self._crossings(positions)
        finally:
            self._prev = prev

    def _crossings(self, positions):
        """Same as RaceProgress._crossings, on Python floats; (None, None) if no drone crossed its
        target gate's plane."""
        n = self.num_drones
        pos = [(float(p[0]), float(p[1]), float(p[2])) for p in positions]
        prev = pos if self._prev is None else self._prev
        passed = hit = None
        for i in range(n):
            j = int(self.target[i])
            cx, cy, cz = self._centre_l[j]
            c, s = self._cos_l[j], self._sin_l[j]
            dx, dy, dz = pos[i][0] - cx, pos[i][1] - cy, pos[i][2] - cz
            x, y, z = c * dx + s * dy, -s * dx + c * dy, dz
            pdx, pdy, pdz = prev[i][0] - cx, prev[i][1] - cy, prev[i][2] - cz
            px, py, pz = c * pdx + s * pdy, -s * pdx + c * pdy, pdz
            if not (px > 0.0 and x <= 0.0):
                continue
            if passed is None:
                passed, hit = np.zeros(n, bool), np.zeros(n, bool)
            frac = px / max(px - x, 1e-9)
            ay, az = abs(py + frac * (y - py)), abs(pz + frac * (z - pz))
            near = math.sqrt(x * x + y * y + z * z) < PASS_RADIUS
            passed[i] = near and ay < PASS_HALF and az < PASS_HALF
            hit[i] = ay < self.outer_half and az < self.outer_half and (ay >= FRAME_HIT_HALF or az >= FRAME_HIT_HALF)
        self._prev = pos
        return passed, hit
