"""The PPO update of one agent (IPPO = every agent runs this on its own samples, with its own
networks and optimizer; the joint objective is the average of the agents' surrogates, paper III-A).

Per minibatch:
    ratio    = exp(log pi(a|o) - log pi_old(a|o))
    L_clip   = -mean(min(ratio A, clip(ratio, 1 - eps, 1 + eps) A))
    V_clip   = V_old + clip(V - V_old, -eps_v, eps_v)
    L_value  = mean(max((V - R)^2, (V_clip - R)^2))          (plain (V - R)^2 without value clip)
    L_bound  = mean(sum_k relu(|mu_k| - 1)^2)                 (keeps the mean inside the action range)
    L        = L_clip + c_v L_value - c_e H[pi] + c_b L_bound
then clip the global grad norm and take an Adam step. With a desired KL the learning rate adapts
(rsl_rl's rule): KL > 2 kl* -> lr / 1.5, KL < kl* / 2 -> lr * 1.5, within [lr_min, lr_max].
"""

from __future__ import annotations

import contextlib

import torch

from cfrace.rl.config import IPPOConfig
from cfrace.rl.models import AgentModels
from cfrace.rl.precision import Precision


def gaussian_kl(mu_old, sigma_old, mu, sigma) -> torch.Tensor:
    """KL(N_old || N_new) summed over action dims, averaged over the batch."""
    kl = torch.log(sigma / sigma_old) + (sigma_old.square() + (mu_old - mu).square()) / (2 * sigma.square()) - 0.5
    return kl.sum(-1).mean()


def make_optimizer(model: AgentModels, lr: float) -> torch.optim.Optimizer:
    """One Adam per agent over its actor and critic (normalisers are buffers, not trained)."""
    params = list(model.actor.parameters()) + list(model.critic.parameters())
    try:  # the fused kernel is 2x faster on CPU for these small networks
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(params, lr=lr)


def forward(model: AgentModels, obs_n: torch.Tensor, critic_n: torch.Tensor, autocast=contextlib.nullcontext):
    """The policy's Gaussian and the values of normalised inputs, with the hidden layers under
    ``autocast`` and the two output layers in float32: a bf16 value of a return in the thousands is off
    by several units (8-bit mantissa), the size of the advantages it is meant to resolve."""
    with autocast():
        h_actor = model.actor.mean_net[:-1](obs_n)
        h_critic = model.critic.net[:-1](critic_n)
    dist = model.actor.distribution(model.actor.mean_net[-1](h_actor.float()))
    return dist, model.critic.net[-1](h_critic.float()).squeeze(-1)


def draw_perms(n: int, cfg: IPPOConfig, generator: torch.Generator | None) -> list[torch.Tensor]:
    """The minibatch shuffles of one update of ``n`` samples: one permutation per epoch (none when
    there are fewer samples than minibatches: no update)."""
    if n < cfg.minibatches:
        return []
    return [torch.randperm(n, generator=generator, device="cpu") for _ in range(cfg.epochs)]


def ppo_update(model: AgentModels, optimizer: torch.optim.Optimizer, batch: dict[str, torch.Tensor],
               cfg: IPPOConfig, lr: float, generator: torch.Generator | None = None,
               precision: Precision | None = None, perms: list[torch.Tensor] | None = None,
               loss_fn=None) -> tuple[dict, float]:
    """Run cfg.epochs x cfg.minibatches updates on ``batch`` (flat alive samples, see
    RolloutStorage.agent_batch). Returns (mean statistics, the learning rate after adaptation).
    The shuffles are ``perms`` (draw_perms) or drawn here from ``generator``; ``loss_fn`` replaces
    minibatch_loss (e.g. its torch.compile'd version, see compiled_loss).

    With a bf16 ``precision`` the two networks' hidden layers run under autocast (forward and
    backward); their output layers, the distribution, the losses and the KL in float32."""
    n = batch["obs"].shape[0]
    stats = {"surrogate": 0.0, "value_loss": 0.0, "entropy": 0.0, "kl": 0.0, "clip_frac": 0.0}
    if n < cfg.minibatches:  # nothing (or almost nothing) alive this rollout
        return {**stats, "samples": float(n)}, lr
    obs_n = model.obs_norm(batch["obs"])          # normalisers are fixed during the update
    critic_n = model.critic_norm(batch["critic"])
    params = [p for g in optimizer.param_groups for p in g["params"]]
    size = n // cfg.minibatches
    autocast = (lambda: precision.autocast(obs_n.device)) if precision is not None else contextlib.nullcontext
    updates = 0
    for perm in perms if perms is not None else draw_perms(n, cfg, generator):
        perm = perm.to(obs_n.device)
        for k in range(cfg.minibatches):
            idx = perm[k * size:(k + 1) * size]
            mb = {key: batch[key][idx] for key in MINIBATCH_KEYS}
            loss, terms, mean, std = (loss_fn or minibatch_loss)(model, obs_n[idx], critic_n[idx], mb, cfg, autocast)
            with torch.no_grad():
                kl = gaussian_kl(batch["mu"][idx], batch["sigma"][idx], mean, std)
            lr = adapt_lr(optimizer, cfg, lr, kl)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
            optimizer.step()
            updates += 1
            for key, term in terms.items():
                stats[key] += term.item()
            stats["kl"] += float(kl)
    stats = {k: v / updates for k, v in stats.items()}
    stats["samples"] = float(n)
    return stats, lr


#: the per-sample fields the losses read
MINIBATCH_KEYS = ("advantages", "returns", "values", "actions", "log_prob")


def minibatch_loss(model: AgentModels, obs_n: torch.Tensor, critic_n: torch.Tensor, mb: dict[str, torch.Tensor],
                   cfg: IPPOConfig, autocast=contextlib.nullcontext):
    """Forward pass and losses of one minibatch: (L, logged terms, Gaussian means (N, 4), stds (N, 4))."""
    dist, value = forward(model, obs_n, critic_n, autocast)
    loss, terms = ppo_losses(dist, value, mb, cfg)
    return loss, terms, dist.mean, dist.stddev


def compiled_loss(backend: str = "inductor"):
    """minibatch_loss through torch.compile (dynamic shapes: the alive sample count, so the minibatch
    size, changes every iteration; the networks' parameters are graph inputs, so one compiled graph
    serves every agent). The first call of each shape family compiles (tens of seconds on a CPU)."""
    return torch.compile(minibatch_loss, dynamic=True, backend=backend)


def adapt_lr(optimizer: torch.optim.Optimizer, cfg: IPPOConfig, lr: float, kl: torch.Tensor) -> float:
    """The adaptive learning rate on the KL to the old policy (nothing without cfg.desired_kl)."""
    if cfg.desired_kl is None:
        return lr
    if kl > 2.0 * cfg.desired_kl:
        lr = max(cfg.lr_min, lr / 1.5)
    elif 0.0 < kl < 0.5 * cfg.desired_kl:
        lr = min(cfg.lr_max, lr * 1.5)
    for group in optimizer.param_groups:
        group["lr"] = lr
    return lr


def ppo_losses(dist, value: torch.Tensor, mb: dict[str, torch.Tensor], cfg: IPPOConfig):
    """The minibatch's loss L and its logged terms (surrogate, value_loss, entropy, clip_frac: 0-d
    tensors). ``mb`` holds MINIBATCH_KEYS for these samples."""
    adv, ret, v_old = mb["advantages"], mb["returns"], mb["values"]
    log_prob = dist.log_prob(mb["actions"]).sum(-1)
    entropy = dist.entropy().sum(-1).mean()
    ratio = torch.exp(log_prob - mb["log_prob"])
    surrogate = -torch.min(ratio * adv, ratio.clamp(1.0 - cfg.clip, 1.0 + cfg.clip) * adv).mean()
    if cfg.value_clip is not None:
        v_clip = v_old + (value - v_old).clamp(-cfg.value_clip, cfg.value_clip)
        value_loss = torch.max((value - ret).square(), (v_clip - ret).square()).mean()
    else:
        value_loss = (value - ret).square().mean()
    loss = surrogate + cfg.value_coef * value_loss - cfg.entropy_coef * entropy
    if cfg.bound_coef > 0.0:  # the env clips actions: a mean beyond +-1 is not what the drone gets
        loss = loss + cfg.bound_coef * (dist.mean.abs() - 1.0).clamp_min(0.0).square().sum(-1).mean()
    clip_frac = ((ratio.detach() - 1.0).abs() > cfg.clip).float().mean()
    return loss, {"surrogate": surrogate, "value_loss": value_loss, "entropy": entropy, "clip_frac": clip_frac}


def ppo_loss(model: AgentModels, batch: dict[str, torch.Tensor], cfg: IPPOConfig) -> float:
    """The full-batch PPO loss (no gradient), for tests and diagnostics."""
    with torch.no_grad():
        dist = model.actor(model.obs_norm(batch["obs"]))
        ratio = torch.exp(dist.log_prob(batch["actions"]).sum(-1) - batch["log_prob"])
        adv = batch["advantages"]
        surrogate = -torch.min(ratio * adv, ratio.clamp(1.0 - cfg.clip, 1.0 + cfg.clip) * adv).mean()
        value = model.critic(model.critic_norm(batch["critic"]))
        return float(surrogate + cfg.value_coef * (value - batch["returns"]).square().mean())
