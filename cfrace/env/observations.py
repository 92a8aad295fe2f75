"""Observations, shared by the environment and the flight loop (one function, no skew).

Layout (paper Sec. III-B and the authors' code), each drone from its own body frame:
    [world position (3), only with obstacles]
    linear velocity in body frame (3)
    rotation matrix world-from-body, row-major (9)
    current target gate's 4 corners in body frame (12)
    next gate's 4 corners in body frame (12)
    [opponent position in body frame (3)]           multi-agent layouts only
    [opponent world velocity rotated to body (3)]   multi-agent layouts only
No normalisation here: the exported actor carries its own normaliser.
Pure array code on torch tensors (the environment, batched, CPU or CUDA) or numpy arrays (the flight
loop, one drone per call: no torch dispatch in the 100 Hz tick). Both run the very same elementwise
float32 operations, so the two give bit-identical observations (tests/test_flight_core.py).
Depends only on states and gate corners, never on simulator internals. Imports no torch: tensors
bring it (the flight path, numpy only, never loads it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from cfrace.arrays import array_module

if TYPE_CHECKING:
    import torch


@dataclass(frozen=True)
class ObsLayout:
    name: str
    world_position: bool  #: prepend the world position (tracks with obstacles)
    opponent: bool        #: append the opponent block (multi-agent)

    @property
    def dim(self) -> int:
        return (3 if self.world_position else 0) + 3 + 9 + 24 + (6 if self.opponent else 0)


LAYOUTS = {
    "race42": ObsLayout("race42", world_position=False, opponent=True),
    "race45_obstacles": ObsLayout("race45_obstacles", world_position=True, opponent=True),
    "solo36": ObsLayout("solo36", world_position=False, opponent=False),
    "solo39_obstacles": ObsLayout("solo39_obstacles", world_position=True, opponent=False),
}


def layout_for(multi_agent: bool, obstacles: bool) -> ObsLayout:
    if multi_agent:
        return LAYOUTS["race45_obstacles" if obstacles else "race42"]
    return LAYOUTS["solo39_obstacles" if obstacles else "solo36"]


def body_frame(rot, vec_world):
    """R^T v for rot (..., 3, 3) world-from-body and v (..., 3) -> (..., 3) (torch or numpy)."""
    return (rot * vec_world[..., None]).sum(-2)


def build_observation(pos, vel, rot, target, gate_corners, layout: ObsLayout, opp_pos=None, opp_vel=None):
    """One observation per drone; all arrays torch tensors or all numpy arrays (same dtype).

    pos, vel: (..., 3) world position (m) and velocity (m/s); rot: (..., 3, 3) world-from-body;
    target: (...,) int index of the drone's current target gate (a Python int for one numpy drone);
    gate_corners: (G, 4, 3) world; opp_pos, opp_vel: (..., 3) the opponent's world position and
    velocity (multi-agent layouts). Returns (..., layout.dim).
    """
    xp = array_module(pos)
    num_gates = gate_corners.shape[0]
    if xp is not np:
        target = target.long()
    cur = gate_corners[target]                       # (..., 4, 3)
    nxt = gate_corners[(target + 1) % num_gates]     # (..., 4, 3)
    rel = xp.stack([cur, nxt], -3) - pos[..., None, None, :]              # (..., 2, 4, 3)
    corners_body = (rot[..., None, None, :, :] * rel[..., None]).sum(-2)   # R^T (c - p)
    batch = tuple(pos.shape[:-1])
    parts = []
    if layout.world_position:
        parts.append(pos)
    parts += [body_frame(rot, vel), rot.reshape(batch + (9,)), corners_body.reshape(batch + (24,))]
    if layout.opponent:
        if opp_pos is None or opp_vel is None:
            raise ValueError(f"layout {layout.name} needs the opponent's position and velocity")
        parts += [body_frame(rot, opp_pos - pos), body_frame(rot, opp_vel)]
    return xp.concatenate(parts, -1)


def build_observations(pos: torch.Tensor, vel: torch.Tensor, rot: torch.Tensor, target: torch.Tensor,
                       gate_corners: torch.Tensor, layout: ObsLayout) -> torch.Tensor:
    """Observations of every drone in a race: tensors shaped (..., N, ...) with N drones on
    the second-to-last batch axis. With N = 2 the opponent of drone i is drone 1 - i."""
    opp_pos = opp_vel = None
    if layout.opponent:
        if pos.shape[-2] != 2:
            raise ValueError(f"layout {layout.name} needs exactly 2 drones, got {pos.shape[-2]}")
        opp_pos, opp_vel = pos.flip(-2), vel.flip(-2)
    return build_observation(pos, vel, rot, target, gate_corners, layout, opp_pos, opp_vel)


def critic_observations(obs: torch.Tensor) -> torch.Tensor:
    """Joint state for the critics: [own obs, opponent obs] per drone, (..., 2, 2 D)."""
    return array_module(obs).cat([obs, obs.flip(-2)], dim=-1)
