"""Reward terms of the paper's four training schemes, as named tensors (each one logged).

All inputs are (E, A) tensors for E worlds and A agents (A >= 2 multi-agent, 1 single-agent).
The paper's schemes with the authors' weights:
- ours (sparse multi-agent): gate pass 10 if leading else 5; lap bonus 50 to the leader only, paid
  once per lap per race; rate cost (0.15 (a1^2 + a2^2) + 0.05 a3^2) dt; contact -0.1 per step;
  crash -2 once.
- ds (dense single-agent): progress 50 (d_prev - d_now) to the next gate centre; rate cost
  0.1 (a1^2 + a2^2 + a3^2) dt; contact -1 per step; crash -10 once.
- ss (sparse single-agent): gate 10, lap 50, rate cost as ours, contact -0.1, crash -2.
- dm (dense multi-agent): ds plus the overtaking term of the paper
  r_ot = 1[d_min < (p_opp - p) < d_max] ((p - p_opp)_t - (p - p_opp)_{t-1}), d_min -5 m, d_max 10 m,
  with p the distance flown along the gate-to-gate polyline; weighted like progress (x50, our choice:
  the paper gives no weight, and at weight 1 the term vanishes next to the x50 progress).
N > 2 drones (our definitions; both reduce to the paper's with two): "leading" is first place
(more gates than every other drone, ties broken by the distance to the next gate), so the lap
bonus and the 10-point gate go to the race leader only; the overtaking term is the paper's term
against each other drone, averaged over the N - 1 opponents (gaining a place on one drone inside
the window pays what passing the only opponent pays in a two-drone race, divided by N - 1, so the
term keeps its weight next to progress whatever N).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import torch

from cfrace.contract import METHODS, MULTI_AGENT_METHODS
from cfrace.errors import ConfigError

MULTI_AGENT = {m: m in MULTI_AGENT_METHODS for m in METHODS}   #: method -> trained two drones per world


@dataclass(frozen=True)
class RewardScales:
    gate_lead: float = 10.0
    gate: float = 5.0            # ours: gate passed while not leading; ss uses gate_lead for every gate
    lap: float = 50.0
    rate_rp: float = 0.15
    rate_yaw: float = 0.05
    contact: float = 0.1
    crash: float = 2.0
    progress: float = 50.0
    dense_rate: float = 0.1
    dense_contact: float = 1.0
    dense_crash: float = 10.0
    overtake: float = 50.0
    ot_min: float = -5.0
    ot_max: float = 10.0


def reward_scales(overrides=()) -> RewardScales:
    """The paper's weights with ``overrides`` ((field, value), ...) over them (`cfrace train --reward`)."""
    names = {f.name for f in fields(RewardScales)}
    for key, _ in overrides:
        if key not in names:
            raise ConfigError(f"--reward {key}: unknown reward weight (one of {', '.join(sorted(names))})")
    return replace(RewardScales(), **{k: float(v) for k, v in overrides})


def parse_reward_overrides(items) -> tuple[tuple[str, float], ...]:
    """``KEY=NUMBER`` strings (`cfrace train --reward`) -> ((key, value), ...), checked."""
    out = []
    for item in items:
        key, sep, text = item.partition("=")
        try:
            value = float(text) if sep else math.nan
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise ConfigError(f"--reward {item!r}: expected KEY=NUMBER, e.g. --reward gate=10")
        out.append((key.strip(), value))
    reward_scales(out)
    return tuple(out)


@dataclass
class RewardInputs:
    action: torch.Tensor        # (E, A, 4) in [-1, 1]
    gates: torch.Tensor         # (E, A) int, gates passed this step
    lap_bonus: torch.Tensor     # (E, A) bool, this agent completed a lap first and leads (paid once per lap)
    leading: torch.Tensor       # (E, A) bool, after the step
    contact: torch.Tensor       # (E, A) bool
    crashed_now: torch.Tensor   # (E, A) bool
    progress: torch.Tensor      # (E, A) m, d_prev - d_now to the target gate centre
    overtake: torch.Tensor      # (E, A) m, change of (p - p_opp) inside the window (0 outside)
    dt: float


def reward_terms(method: str, x: RewardInputs, k: RewardScales = RewardScales()) -> dict[str, torch.Tensor]:
    """Named reward terms (E, A) for ``method``; their sum is the reward."""
    a = x.action
    f = lambda b: b.to(a.dtype)
    if method in ("ours", "ss"):
        if method == "ours":
            gate = torch.where(x.leading, k.gate_lead, k.gate) * x.gates.to(a.dtype)
        else:
            gate = k.gate_lead * x.gates.to(a.dtype)
        return {
            "gate": gate,
            "lap": k.lap * f(x.lap_bonus),
            "rate": -(k.rate_rp * (a[..., 1] ** 2 + a[..., 2] ** 2) + k.rate_yaw * a[..., 3] ** 2) * x.dt,
            "contact": -k.contact * f(x.contact),
            "crash": -k.crash * f(x.crashed_now),
        }
    if method in ("ds", "dm"):
        terms = {
            "progress": k.progress * x.progress,
            "rate": -k.dense_rate * (a[..., 1:4] ** 2).sum(-1) * x.dt,
            "contact": -k.dense_contact * f(x.contact),
            "crash": -k.dense_crash * f(x.crashed_now),
        }
        if method == "dm":
            terms["overtake"] = k.overtake * x.overtake
        return terms
    raise ValueError(f"unknown method {method!r} (expected one of {', '.join(METHODS)})")


def leading(gates_passed: torch.Tensor, dist_to_target: torch.Tensor, alive: torch.Tensor) -> torch.Tensor:
    """(E, A) bool: first place: more gates passed than every other drone; on a tie, closer to its own
    next gate. A crashed drone never leads a live one. Single agent (A = 1): always leading."""
    n = gates_passed.shape[-1]
    if n == 1:
        return torch.ones_like(alive)
    score = gates_passed.to(dist_to_target.dtype) * 1000.0 - dist_to_target
    score = torch.where(alive, score, torch.full_like(score, -1e9))
    if n == 2:
        return score > score.flip(-1)
    others = score.unsqueeze(-2).expand(*score.shape, n)                        # [i, j] = score_j
    eye = torch.eye(n, dtype=torch.bool, device=score.device)
    return score > torch.where(eye, torch.full_like(others, -torch.inf), others).amax(-1)


def overtaking(track_pos: torch.Tensor, prev_track_pos: torch.Tensor, k: RewardScales = RewardScales()) -> torch.Tensor:
    """(E, A) m: paper's r_ot before weighting; track_pos p (E, A) along the polyline. With A > 2
    the term against each other drone, averaged over the A - 1 of them (module docstring)."""
    n = track_pos.shape[-1]
    if n == 2:
        gap = track_pos.flip(-1) - track_pos                 # p_opp - p
        inside = (gap > k.ot_min) & (gap < k.ot_max)
        rel, prev_rel = track_pos - track_pos.flip(-1), prev_track_pos - prev_track_pos.flip(-1)
        return inside.to(track_pos.dtype) * (rel - prev_rel)
    gap = track_pos.unsqueeze(-2) - track_pos.unsqueeze(-1)              # [i, j] = p_j - p_i
    prev_gap = prev_track_pos.unsqueeze(-2) - prev_track_pos.unsqueeze(-1)
    inside = (gap > k.ot_min) & (gap < k.ot_max)                          # the diagonal (0) is inside
    gained = inside.to(track_pos.dtype) * (prev_gap - gap)               # (p_i - p_j)_t - (p_i - p_j)_{t-1}
    return gained.sum(-1) / (n - 1)                                       # the diagonal adds 0
