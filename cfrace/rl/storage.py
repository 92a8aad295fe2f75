"""Rollout storage and generalised advantage estimation (GAE).

Everything is shaped (T, E, A, ...): rollout step, world, agent. One rollout holds every agent;
the update then takes each agent's alive samples.

Done flags: done_t = terminated_t | truncated_t | ~alive_t. A dead step (the drone crashed earlier
in the race and waits for the other one) is done and masked out of every loss. On truncation
(time limit) the runner adds gamma * V(s_final) to r_t before the GAE, so the cut is not treated
as a real end (bootstrap on truncation).
"""

from __future__ import annotations

import torch


def gae(rewards: torch.Tensor, values: torch.Tensor, dones: torch.Tensor, last_values: torch.Tensor,
        gamma: float, lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    """GAE(gamma, lambda) backwards in time.

    rewards, values, dones: (T, ...); last_values: (...) = V(s_T) after the last step.
        delta_t = r_t + gamma V(s_{t+1}) (1 - done_t) - V(s_t)
        A_t     = delta_t + gamma lambda (1 - done_t) A_{t+1}
        R_t     = A_t + V(s_t)                       (value targets)
    Returns (advantages, returns), both (T, ...).
    """
    steps = rewards.shape[0]
    adv = torch.zeros_like(rewards)
    next_adv = torch.zeros_like(last_values)
    next_value = last_values
    not_done = 1.0 - dones.float()
    for t in reversed(range(steps)):
        delta = rewards[t] + gamma * next_value * not_done[t] - values[t]
        next_adv = delta + gamma * lam * not_done[t] * next_adv
        adv[t] = next_adv
        next_value = values[t]
    return adv, adv + values


class RolloutStorage:
    """Fixed-size buffers for one rollout of T steps of E worlds with A agents."""

    FIELDS = ("obs", "critic", "actions", "log_prob", "values", "mu", "sigma", "rewards", "dones", "alive")

    def __init__(self, steps: int, num_envs: int, num_agents: int, obs_dim: int, critic_dim: int, device):
        t, e, a = steps, num_envs, num_agents
        f = dict(device=device, dtype=torch.float32)
        self.steps = steps
        self.obs = torch.zeros(t, e, a, obs_dim, **f)          # actor inputs (raw, unnormalised)
        self.critic = torch.zeros(t, e, a, critic_dim, **f)    # critic inputs (raw)
        self.actions = torch.zeros(t, e, a, 4, **f)            # sampled (unclipped) actions
        self.log_prob = torch.zeros(t, e, a, **f)              # log pi_old(a|o)
        self.values = torch.zeros(t, e, a, **f)                # V_old(s)
        self.mu = torch.zeros(t, e, a, 4, **f)                 # old Gaussian mean (for the KL)
        self.sigma = torch.zeros(t, e, a, 4, **f)              # old Gaussian std
        self.rewards = torch.zeros(t, e, a, **f)               # r_t (+ gamma V(final) on truncation)
        self.dones = torch.zeros(t, e, a, dtype=torch.bool, device=device)
        self.alive = torch.zeros(t, e, a, dtype=torch.bool, device=device)
        self.advantages = torch.zeros(t, e, a, **f)
        self.returns = torch.zeros(t, e, a, **f)

    def add(self, t: int, **items: torch.Tensor) -> None:
        for name, value in items.items():
            getattr(self, name)[t] = value

    def compute_returns(self, last_values: torch.Tensor, gamma: float, lam: float) -> None:
        """last_values (E, A) = V(s_T) of the observation after the last stored step."""
        self.advantages, self.returns = gae(self.rewards, self.values, self.dones, last_values, gamma, lam)

    def agent_batch(self, agent: int) -> dict[str, torch.Tensor]:
        """Flat (N, ...) tensors of agent ``agent``'s alive samples; advantages normalised over them."""
        mask = self.alive[:, :, agent]                          # (T, E)
        batch = {name: getattr(self, name)[:, :, agent][mask]
                 for name in ("obs", "critic", "actions", "log_prob", "values", "mu", "sigma",
                              "advantages", "returns")}
        adv = batch["advantages"]
        if adv.numel() > 1:
            batch["advantages"] = (adv - adv.mean()) / (adv.std() + 1e-8)
        return batch
