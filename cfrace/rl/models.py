"""Networks of one agent: Gaussian actor, critic, running observation normalisers.

IPPO (paper Sec. III-A): every agent owns an actor pi_i(a | o_i), a critic V_i(s) that sees the
joint state s = [o_i, o_j] (critic obs), and their optimizers. Nothing is shared between agents.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import nn

from cfrace.contract import NORM_CLIP, NORM_EPS


def mlp(in_dim: int, hidden: Sequence[int], out_dim: int, out_gain: float = 1.0) -> nn.Sequential:
    """Linear -> ELU -> ... -> Linear. Orthogonal init (sqrt 2 hidden, out_gain on the last layer)."""
    layers: list[nn.Module] = []
    sizes = [in_dim, *hidden]
    for a, b in zip(sizes[:-1], sizes[1:]):
        lin = nn.Linear(a, b)
        nn.init.orthogonal_(lin.weight, math.sqrt(2.0))
        nn.init.zeros_(lin.bias)
        layers += [lin, nn.ELU()]
    last = nn.Linear(sizes[-1], out_dim)
    nn.init.orthogonal_(last.weight, out_gain)
    nn.init.zeros_(last.bias)
    layers.append(last)
    return nn.Sequential(*layers)


class RunningNorm(nn.Module):
    """Running mean / variance of observations (Chan et al. parallel update, float64 statistics).

    forward: y = clip((x - mean) / sqrt(var + eps), -10, 10), exactly what the ONNX graph does.
    """

    def __init__(self, dim: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim, dtype=torch.float64))  # (D,)
        self.register_buffer("var", torch.ones(dim, dtype=torch.float64))    # (D,)
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))  # samples seen

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Fold a batch x (N, D) into the statistics (population variance)."""
        x = x.reshape(-1, x.shape[-1]).double()
        n = x.shape[0]
        if n == 0:
            return
        b_mean = x.mean(0)
        b_var = x.var(0, unbiased=False)
        total = self.count + n
        delta = b_mean - self.mean
        # M2 = M2_a + M2_b + delta^2 n_a n_b / (n_a + n_b)
        m2 = self.var * self.count + b_var * n + delta.square() * self.count * n / total
        self.mean.add_(delta * n / total)
        self.var.copy_(m2 / total)
        self.count.copy_(total)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        std = torch.sqrt(self.var.float() + NORM_EPS)
        return ((x - self.mean.float()) / std).clamp(-NORM_CLIP, NORM_CLIP)


class Actor(nn.Module):
    """Gaussian policy N(mu(o), diag(std)^2), std = exp(log_std) state-independent, at most ``std_max``
    when that is set (the exploration-noise schedule, config.std_cap; None: no cap)."""

    def __init__(self, obs_dim: int, hidden: Sequence[int], init_std: float = 1.0, action_dim: int = 4):
        super().__init__()
        self.mean_net = mlp(obs_dim, hidden, action_dim, out_gain=0.01)
        self.log_std = nn.Parameter(torch.full((action_dim,), math.log(init_std)))
        self.std_max: float | None = None

    def forward(self, obs_n: torch.Tensor) -> torch.distributions.Normal:
        return self.distribution(self.mean_net(obs_n))

    def std(self) -> torch.Tensor:
        """(4,) the action std the policy samples with."""
        std = self.log_std.exp()
        return std if self.std_max is None else std.clamp(max=self.std_max)

    def distribution(self, mu: torch.Tensor) -> torch.distributions.Normal:
        """The Gaussian around means ``mu`` (N, 4), in mu's dtype (float32 for log-probs and losses)."""
        return torch.distributions.Normal(mu, self.std().expand_as(mu))


class Critic(nn.Module):
    """V(s) from the (normalised) joint state."""

    def __init__(self, critic_dim: int, hidden: Sequence[int]):
        super().__init__()
        self.net = mlp(critic_dim, hidden, 1, out_gain=1.0)

    def forward(self, critic_n: torch.Tensor) -> torch.Tensor:
        return self.net(critic_n).squeeze(-1)


class AgentModels(nn.Module):
    """Everything one agent owns: actor, critic and both normalisers."""

    def __init__(self, obs_dim: int, critic_dim: int, actor_hidden: Sequence[int],
                 critic_hidden: Sequence[int], init_std: float):
        super().__init__()
        self.actor = Actor(obs_dim, actor_hidden, init_std)
        self.critic = Critic(critic_dim, critic_hidden)
        self.obs_norm = RunningNorm(obs_dim)
        self.critic_norm = RunningNorm(critic_dim)

    @torch.no_grad()
    def act(self, obs: torch.Tensor, critic: torch.Tensor, deterministic: bool = False):
        """obs (N, D), critic (N, C) -> action (N, 4) (unclipped sample), log_prob (N,), value (N,)."""
        dist = self.actor(self.obs_norm(obs))
        action = dist.mean if deterministic else dist.sample()
        return action, dist.log_prob(action).sum(-1), self.critic(self.critic_norm(critic))

    @torch.no_grad()
    def value(self, critic: torch.Tensor) -> torch.Tensor:
        return self.critic(self.critic_norm(critic))
