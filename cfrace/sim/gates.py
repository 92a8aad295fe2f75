"""Gate passing: one rule for the simulator, the environment and the flight loop.

facts.md: a gate is passed when the drone's x in the gate frame goes from > 0 to <= 0 (it
approaches from the +n side and flies along -n), within 1.0 m of the centre, with |y| < 0.5 and
|z| < 0.5 in the gate frame. Crossing the target gate's plane with |y| or |z| >= 0.4 (inside the
outer frame) is a gate-frame hit, a terminal crash.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

PASS_HALF = 0.5        #: m, |y|, |z| limit in the gate frame for a pass
PASS_RADIUS = 1.0      #: m, distance from the centre within which a crossing counts
FRAME_HIT_HALF = 0.4   #: m, crossing the target plane with |y| or |z| >= this hits the frame


def to_gate_frame(pos: torch.Tensor, gate_pose: torch.Tensor) -> torch.Tensor:
    """World position (..., 3) -> gate-frame position (..., 3) for gate poses (..., 4) [x, y, z, yaw]."""
    d = pos - gate_pose[..., :3]
    c, s = torch.cos(gate_pose[..., 3]), torch.sin(gate_pose[..., 3])
    x = c * d[..., 0] + s * d[..., 1]
    y = -s * d[..., 0] + c * d[..., 1]
    return torch.stack([x, y, d[..., 2]], dim=-1)


def crossing(prev_local: torch.Tensor, local: torch.Tensor, outer_half: float = 0.7):
    """(passed, frame_hit) bool tensors (...,) from gate-frame positions before and after a step."""
    crossed = (prev_local[..., 0] > 0.0) & (local[..., 0] <= 0.0)
    # the plane crossing point, interpolated between the two samples
    frac = prev_local[..., 0] / (prev_local[..., 0] - local[..., 0]).clamp_min(1e-9)
    yz = prev_local[..., 1:] + frac.unsqueeze(-1) * (local[..., 1:] - prev_local[..., 1:])
    ay, az = yz[..., 0].abs(), yz[..., 1].abs()
    near = torch.linalg.vector_norm(local, dim=-1) < PASS_RADIUS
    passed = crossed & near & (ay < PASS_HALF) & (az < PASS_HALF)
    inside_outer = (ay < outer_half) & (az < outer_half)
    frame_hit = crossed & inside_outer & ((ay >= FRAME_HIT_HALF) | (az >= FRAME_HIT_HALF))
    return passed, frame_hit


@dataclass
class RaceProgress:
    """Per-drone race progress for the flight loop (numpy in, same rule as the simulator).

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
        pos = torch.as_tensor(np.asarray(positions, dtype=np.float64))
        cur_gate = torch.as_tensor(self.gates, dtype=torch.float64)[torch.as_tensor(self.target)]
        prev = pos if self._prev is None else self._prev
        passed, hit = crossing(to_gate_frame(prev, cur_gate), to_gate_frame(pos, cur_gate), self.outer_half)
        self._prev = pos.clone()
        return passed.numpy(), hit.numpy()

    def distance_to_target(self, positions: np.ndarray) -> np.ndarray:
        return np.linalg.norm(np.asarray(positions) - self.gates[self.target, :3], axis=-1)

    def leader(self, positions: np.ndarray) -> int:
        """Index of the leading drone: more gates passed; tie -> closer to its own next gate."""
        d = self.distance_to_target(positions)
        order = sorted(range(len(d)), key=lambda i: (-self.gates_passed[i], d[i]))
        return order[0]
