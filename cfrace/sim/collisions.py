"""Contacts of the drone (a sphere of the collision box's half-width) with yawed boxes and drones.

Gate frames are four bar boxes per gate (touching one is a gate-frame hit, a terminal crash);
obstacles are boxes standing on the floor (touching one is a contact: the drone is pushed out and
its velocity into the box removed; long contact is a crash); two drones closer than two radii are
in contact (pushed apart, normal velocities averaged).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

#: m; touching (a contact) reaches this far beyond the push-out distance, so that a drone resting
#: against a wall or another drone stays in contact
CONTACT_MARGIN = 1e-3


class Boxes(NamedTuple):
    centre: torch.Tensor  # (B, 3) m
    half: torch.Tensor    # (B, 3) m
    cos: torch.Tensor     # (B,) cos yaw
    sin: torch.Tensor     # (B,) sin yaw


def make_boxes(centre, half, yaw, device, dtype=torch.float32) -> Boxes:
    c = torch.as_tensor(centre, dtype=dtype, device=device).reshape(-1, 3)
    h = torch.as_tensor(half, dtype=dtype, device=device).reshape(-1, 3)
    y = torch.as_tensor(yaw, dtype=dtype, device=device).reshape(-1)
    return Boxes(c, h, torch.cos(y), torch.sin(y))


def _to_local(pos: torch.Tensor, b: Boxes) -> torch.Tensor:
    """(W, D, 3) world -> (W, D, B, 3) in each box frame."""
    d = pos.unsqueeze(-2) - b.centre
    lx = b.cos * d[..., 0] + b.sin * d[..., 1]
    ly = -b.sin * d[..., 0] + b.cos * d[..., 1]
    return torch.stack([lx, ly, d[..., 2]], dim=-1)


def box_distance(pos: torch.Tensor, b: Boxes) -> torch.Tensor:
    """(W, D, B) distance from each drone centre to each box surface (0 inside)."""
    local = _to_local(pos, b)
    excess = (local.abs() - b.half).clamp_min(0.0)
    return torch.linalg.vector_norm(excess, dim=-1)


def any_box_hit(pos: torch.Tensor, b: Boxes, radius: float) -> torch.Tensor:
    """(W, D) bool: the drone sphere touches any box."""
    if b.centre.shape[0] == 0:
        return torch.zeros(pos.shape[:-1], dtype=torch.bool, device=pos.device)
    return (box_distance(pos, b) < radius).any(-1)


def push_out_of_boxes(pos: torch.Tensor, vel: torch.Tensor, b: Boxes, radius: float):
    """Resolve sphere-box contacts box by box. Returns (pos, vel, contact (W, D) bool)."""
    contact = torch.zeros(pos.shape[:-1], dtype=torch.bool, device=pos.device)
    for k in range(b.centre.shape[0]):
        c, s, h, ctr = b.cos[k], b.sin[k], b.half[k], b.centre[k]
        d = pos - ctr
        lx = c * d[..., 0] + s * d[..., 1]
        ly = -s * d[..., 0] + c * d[..., 1]
        local = torch.stack([lx, ly, d[..., 2]], dim=-1)
        clamped = torch.maximum(torch.minimum(local, h), -h)
        diff = local - clamped
        dist = torch.linalg.vector_norm(diff, dim=-1, keepdim=True)
        # inside the box: leave along the axis of least penetration
        pen = h - local.abs()
        axis = torch.nn.functional.one_hot(pen.argmin(-1), 3).to(pos.dtype)
        inside_n = axis * torch.where(local >= 0, 1.0, -1.0)
        outside = dist > 1e-9
        n_local = torch.where(outside, diff / dist.clamp_min(1e-9), inside_n)
        hit = (dist.squeeze(-1) < radius)
        touch = (dist.squeeze(-1) < radius + CONTACT_MARGIN)
        new_local = clamped + n_local * radius
        # back to world; only pushed drones move (a round trip through the box frame would round the others)
        wx = c * new_local[..., 0] - s * new_local[..., 1] + ctr[0]
        wy = s * new_local[..., 0] + c * new_local[..., 1] + ctr[1]
        pos = torch.where(hit.unsqueeze(-1), torch.stack([wx, wy, new_local[..., 2] + ctr[2]], dim=-1), pos)
        n_world = torch.stack([c * n_local[..., 0] - s * n_local[..., 1], s * n_local[..., 0] + c * n_local[..., 1],
                               n_local[..., 2]], dim=-1)
        vn = (vel * n_world).sum(-1, keepdim=True)
        vel = torch.where(hit.unsqueeze(-1) & (vn < 0), vel - vn * n_world, vel)
        contact = contact | touch
    return pos, vel, contact


def drone_contacts(pos: torch.Tensor, vel: torch.Tensor, active: torch.Tensor, radius: float):
    """Pairwise drone-drone contact among active drones. pos, vel (W, D, 3); active (W, D) bool.
    Returns (pos, vel, contact (W, D) bool)."""
    n = pos.shape[-2]
    if n < 2:
        return pos, vel, torch.zeros(pos.shape[:-1], dtype=torch.bool, device=pos.device)
    diff = pos.unsqueeze(-2) - pos.unsqueeze(-3)                 # (W, D, D, 3) p_i - p_j
    dist = torch.linalg.vector_norm(diff, dim=-1)               # (W, D, D)
    eye = torch.eye(n, dtype=torch.bool, device=pos.device)
    pair = active.unsqueeze(-1) & active.unsqueeze(-2) & ~eye
    touching = pair & (dist < 2.0 * radius)
    contact = pair & (dist < 2.0 * (radius + CONTACT_MARGIN))
    normal = diff / dist.clamp_min(1e-6).unsqueeze(-1)          # from j to i
    depth = (2.0 * radius - dist).clamp_min(0.0) * touching
    pos = pos + 0.5 * (depth.unsqueeze(-1) * normal).sum(-2)
    rel_vn = ((vel.unsqueeze(-2) - vel.unsqueeze(-3)) * normal).sum(-1)   # (W, D, D) closing if < 0
    closing = touching & (rel_vn < 0)
    vel = vel - 0.5 * ((rel_vn * closing).unsqueeze(-1) * normal).sum(-2)
    return pos, vel, contact.any(-1)
