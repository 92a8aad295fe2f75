"""Observations, shared by the environment and the flight loop (one function, no skew).

Layout (the paper, Sec. III-B, and the authors' code,
Jirl-upenn/AgileFlight_MultiAgent ma_quadcopter_env.py), each drone from its own body frame:
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


def _norm(x):
    """|x| over the last axis (torch or numpy)."""
    if array_module(x) is np:
        return np.linalg.norm(x, axis=-1)
    import torch

    return torch.linalg.vector_norm(x, dim=-1)


def polyline(gates):
    """The race line through the gate centres of gates (G, 4): (cum (G,) m from gate 0 to gate g,
    lap length m). Torch or numpy."""
    xp = array_module(gates)
    seg = _norm(gates[:, :3] - xp.roll(gates, 1, 0)[:, :3])
    parts = [gates[:1, 0] * 0, seg[1:].cumsum(0)]                     # 0 m at gate 0, then the sums
    cum = np.concatenate(parts) if xp is np else xp.cat(parts)
    return cum, float(seg.sum())


def track_position(gates, cum, lap_len: float, start_gate, gates_passed, target, pos):
    """(..., D) m flown along the race line since the start gate: the gates passed along the line,
    less the straight distance still to the target gate. start_gate (...,), gates_passed and target
    (..., D), pos (..., D, 3); torch or numpy (the flight loop: one race, numpy)."""
    xp = array_module(pos)
    g = gates.shape[0]
    absolute = start_gate[..., None] + gates_passed     # index of the target gate
    laps = (absolute // g).astype(np.float64) if xp is np else (absolute // g).float()
    coord = laps * lap_len + cum[absolute % g]
    return coord - cum[start_gate][..., None] - _norm(pos - gates[target][..., :3])


#: rules for which one opponent each drone observes in a field of N > 2 drones (with 2 drones
#: every rule gives the other drone). Keys between candidates j of drone i, smallest wins:
#:   nearest  the nearest drone in space, |p_j - p_i|
#:   ahead    the nearest drone ahead on the track (smallest s_j - s_i > 0, s = metres flown along
#:            the gate polyline); the leader, with nobody ahead, sees the nearest one behind it
#:   track    the nearest drone along the track, |s_j - s_i|, ahead or behind
#: A crashed drone is chosen only when every other drone crashed too.
OPPONENT_RULES = ("nearest", "ahead", "track")
DEFAULT_OPPONENT_RULE = "nearest"   #: measured in docs/evaluation.md ("Swarm races: which opponent")
_BEHIND = 1.0e4   #: m, ranks every drone behind after every drone ahead ("ahead")
_DOWN = 1.0e6     #: m, ranks crashed drones after live ones
_SELF = 1.0e9


def choose_opponents(pos, track_pos, alive, rule: str = DEFAULT_OPPONENT_RULE):
    """Index (..., N) of the opponent each drone observes; torch or numpy arrays.

    pos (..., N, 3) world positions (m); track_pos (..., N) metres along the gate polyline from a
    common origin (only differences are used; the "nearest" rule ignores it); alive (..., N) bool.
    """
    xp = array_module(pos)
    n = pos.shape[-2]
    if rule not in OPPONENT_RULES:
        raise ValueError(f"unknown opponent rule {rule!r} (choose from {', '.join(OPPONENT_RULES)})")
    if rule == "nearest":
        diff = pos[..., None, :, :] - pos[..., :, None, :]          # [i, j] = p_j - p_i
        key = (diff * diff).sum(-1)
    else:
        gap = track_pos[..., None, :] - track_pos[..., :, None]     # [i, j] = s_j - s_i
        key = xp.where(gap > 0, gap, _BEHIND - gap) if rule == "ahead" else abs(gap)
    key = key + xp.where(alive[..., None, :], 0.0, _DOWN) + _SELF * (xp.eye(n) if xp is np else
                                                                        xp.eye(n, device=pos.device))
    return key.argmin(-1) if xp is not np else np.argmin(key, -1)


def gather_drones(x, idx):
    """x (..., N, K) -> (..., M, K): x[..., idx[..., m], :] for idx (..., M) (torch or numpy)."""
    xp = array_module(x)
    if xp is np:
        return np.take_along_axis(x, idx[..., None], -2)
    return x.gather(-2, idx[..., None].expand(*idx.shape, x.shape[-1]))


def build_observations(pos: torch.Tensor, vel: torch.Tensor, rot: torch.Tensor, target: torch.Tensor,
                       gate_corners: torch.Tensor, layout: ObsLayout, opponent: torch.Tensor | None = None
                       ) -> torch.Tensor:
    """Observations of every drone in a race: tensors shaped (..., N, ...) with N drones on
    the second-to-last batch axis. ``opponent`` (..., N): the drone each one observes
    (choose_opponents); None with N = 2: the other drone (drone 1 - i)."""
    opp_pos = opp_vel = None
    if layout.opponent:
        n = pos.shape[-2]
        if opponent is None:
            if n != 2:
                raise ValueError(f"layout {layout.name} with {n} drones needs the opponent of each (choose_opponents)")
            opp_pos, opp_vel = pos.flip(-2), vel.flip(-2)
        else:
            opp_pos, opp_vel = gather_drones(pos, opponent), gather_drones(vel, opponent)
    return build_observation(pos, vel, rot, target, gate_corners, layout, opp_pos, opp_vel)


def critic_order(opponent: torch.Tensor) -> torch.Tensor:
    """(..., N, N) drone order of each drone's joint state: itself, the opponent it observes, then
    the others by index. With N = 2: [i, 1 - i]."""
    import torch

    n = opponent.shape[-1]
    j = torch.arange(n, device=opponent.device)
    i = j[:, None]
    key = torch.where(j == i, 0, torch.where(j == opponent[..., None], 1, 2 + j))   # (..., N, N)
    return key.argsort(-1)


def critic_observations(obs: torch.Tensor, opponent: torch.Tensor | None = None) -> torch.Tensor:
    """Joint state for the critics, (..., N, N D): per drone its own observation, the observed
    opponent's, then the other drones' (critic_order). None with N = 2: [own obs, other obs]."""
    if opponent is None:
        return array_module(obs).cat([obs, obs.flip(-2)], dim=-1)
    order = critic_order(opponent)                                    # (..., N, N)
    n, d = obs.shape[-2], obs.shape[-1]
    joint = obs[..., None, :, :].expand(*obs.shape[:-2], n, n, d)
    joint = joint.gather(-2, order[..., None].expand(*order.shape, d))
    return joint.reshape(*obs.shape[:-2], n, n * d)
