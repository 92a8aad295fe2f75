"""Gate passing: one rule for the simulator, the environment and the flight loop.

The authors' rule: a gate is passed when the drone's x in the gate frame goes from > 0 to <= 0 (it
approaches from the +n side and flies along -n), within 1.0 m of the centre, with |y| < 0.5 and
|z| < 0.5 in the gate frame. Crossing the target gate's plane with |y| or |z| >= 0.4 (inside the
outer frame) is a gate-frame hit, a terminal crash.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cfrace.arrays import array_module

PASS_HALF = 0.5        #: m, |y|, |z| limit in the gate frame for a pass
PASS_RADIUS = 1.0      #: m, distance from the centre within which a crossing counts
FRAME_HIT_HALF = 0.4   #: m, crossing the target plane with |y| or |z| >= this hits the frame


def to_gate_frame(pos, gate_pose):
    """World position (..., 3) -> gate-frame position (..., 3) for gate poses (..., 4) [x, y, z, yaw]
    (torch tensors or numpy arrays)."""
    xp = array_module(pos)
    d = pos - gate_pose[..., :3]
    c, s = xp.cos(gate_pose[..., 3]), xp.sin(gate_pose[..., 3])
    x = c * d[..., 0] + s * d[..., 1]
    y = -s * d[..., 0] + c * d[..., 1]
    return xp.stack([x, y, d[..., 2]], -1)


def crossing(prev_local, local, outer_half: float = 0.7):
    """(passed, frame_hit) bool arrays (...,) from gate-frame positions before and after a step
    (torch tensors or numpy arrays). The rule; the C kernel gets its constants as build flags
    (cfrace.sim.ckernel.rule_defines) and cfrace.flight.loop.gate_progress repeats it on floats for one drone."""
    xp = array_module(local)
    crossed = (prev_local[..., 0] > 0.0) & (local[..., 0] <= 0.0)
    # the plane crossing point, interpolated between the two samples
    gap = prev_local[..., 0] - local[..., 0]
    frac = prev_local[..., 0] / (np.maximum(gap, 1e-9) if xp is np else gap.clamp_min(1e-9))
    yz = prev_local[..., 1:] + frac[..., None] * (local[..., 1:] - prev_local[..., 1:])
    ay, az = abs(yz[..., 0]), abs(yz[..., 1])
    near = (np.linalg.norm(local, axis=-1) if xp is np else xp.linalg.vector_norm(local, dim=-1)) < PASS_RADIUS
    passed = crossed & near & (ay < PASS_HALF) & (az < PASS_HALF)
    inside_outer = (ay < outer_half) & (az < outer_half)
    frame_hit = crossed & inside_outer & ((ay >= FRAME_HIT_HALF) | (az >= FRAME_HIT_HALF))
    return passed, frame_hit


@dataclass
class RaceProgress:
    """Per-drone race progress (numpy, float64; the simulator's rule), the reference of
    cfrace.flight.loop.gate_progress.FastRaceProgress.

    Call update(t, positions) every tick with world positions (N, 3)."""

    gates: np.ndarray          #: (G, 4) gate poses in race order
    num_drones: int
    outer_half: float = 0.7
    start_gate: int = 0
    target: np.ndarray = field(init=False)        #: (N,) next gate index
    gates_passed: np.ndarray = field(init=False)  #: (N,)
    laps: np.ndarray = field(init=False)          #: (N,)
    lap_times: list = field(init=False)           #: per drone, list of lap durations s
    frame_hits: np.ndarray = field(init=False)    #: (N,)
    _prev: np.ndarray | None = field(init=False, default=None)
    _lap_start: np.ndarray = field(init=False)

    def __post_init__(self):
        n = self.num_drones
        self.target = np.full(n, self.start_gate, dtype=np.int64)
        self.gates_passed = np.zeros(n, dtype=np.int64)
        self.laps = np.zeros(n, dtype=np.int64)
        self.frame_hits = np.zeros(n, dtype=np.int64)
        self.lap_times = [[] for _ in range(n)]
        self._lap_start = np.full(n, np.nan)

    def update(self, t: float, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Returns (passed, lap_done, frame_hit) bool arrays (N,) for this tick."""
        if np.isnan(self._lap_start).all():
            self._lap_start[:] = t
        passed, hit = self._crossings(positions)
        return self._book(t, passed, hit)

    def _book(self, t: float, passed: np.ndarray, hit: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Targets, gates, laps and lap times after this tick's crossings."""
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

    def _crossings(self, positions) -> tuple[np.ndarray, np.ndarray]:
        """(passed, frame_hit) bool (N,) against each drone's target gate since the last call."""
        pos = np.array(positions, dtype=np.float64)
        cur_gate = np.asarray(self.gates, dtype=np.float64)[self.target]
        prev = pos if self._prev is None else self._prev
        passed, hit = crossing(to_gate_frame(prev, cur_gate), to_gate_frame(pos, cur_gate), self.outer_half)
        self._prev = pos
        return passed, hit

    def distance_to_target(self, positions: np.ndarray) -> np.ndarray:
        return np.linalg.norm(np.asarray(positions) - self.gates[self.target, :3], axis=-1)

    def leader(self, positions: np.ndarray) -> int:
        """Index of the leading drone: more gates passed; tie -> closer to its own next gate."""
        d = self.distance_to_target(positions)
        order = sorted(range(len(d)), key=lambda i: (-self.gates_passed[i], d[i]))
        return order[0]
