"""The IPPO runner: rollout -> GAE -> per-agent PPO update -> normaliser update, with exact
checkpoint/resume state. The training loop with logs and budgets is in cfrace/rl/train.py.

One iteration (everything batched over E worlds, one forward pass per agent and step):
    for t in 0..T-1:
        a_i ~ pi_i(. | norm_i(o_i)),  V_i(norm_i'(s_i))              for every agent i
        env.step(a) -> r, terminated, truncated, alive, next obs (auto-reset), final critic obs
        r_t += gamma V_i(s_final) where truncated (bootstrap on the time limit)
        done_t = terminated | truncated | ~alive                      (dead steps are masked)
    GAE per agent, advantages normalised over its alive samples, PPO update per agent,
    then fold this rollout's alive observations into each agent's running normalisers.

With ``cfg.shared`` every drone of a world is flown by ONE set of networks (actor, critic and their
normalisers): one forward pass for all drones, one PPO update on all drones' samples (advantages
normalised per drone, as without sharing). ``agents`` then holds one model; ``model(a)`` is the one
flying drone a either way.
"""

from __future__ import annotations

import random
import time
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from torch import nn

from cfrace.rl.config import IPPOConfig, std_cap
from cfrace.rl.ippo import compiled_loss, draw_perms, make_optimizer, ppo_update
from cfrace.rl.models import AgentModels
from cfrace.rl.precision import Precision
from cfrace.rl.storage import RolloutStorage


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class _RolloutSums:
    """What one rollout adds up: seconds in the simulator and in inference, reward per drone, reward
    terms over alive steps, the env's stats per step and the returns of the episodes that ended."""

    def __init__(self, num_agents: int, device: torch.device):
        self.sim_s = self.infer_s = 0.0
        self.term_sums: dict[str, torch.Tensor] = defaultdict(lambda: torch.zeros(num_agents, device=device))
        self.stat_sums: dict[str, list[float]] = defaultdict(list)
        self.returns: list[list[float]] = [[] for _ in range(num_agents)]
        self.reward_sum = torch.zeros(num_agents, device=device)

    def book(self, runner: "Runner", res, alive: torch.Tensor, reward: torch.Tensor) -> None:
        """Episode bookkeeping of one step (raw rewards, before the bootstrap)."""
        runner.ep_return += reward
        ended = alive & (res.terminated | res.truncated)
        if ended.any():
            for a in range(runner.num_agents):
                self.returns[a] += runner.ep_return[:, a][ended[:, a]].tolist()
            runner.ep_return[ended] = 0.0
        self.reward_sum += reward.sum(0)
        for name, value in res.terms.items():
            self.term_sums[name] += torch.where(alive, value, 0.0).sum(0)
        for name, value in res.stats.items():
            self.stat_sums[name].append(float(value))


class Runner:
    """Owns the agents, their optimizers, the rollout buffer and the env's current observations."""

    def __init__(self, env, cfg: IPPOConfig, seed: int = 0):
        self.env, self.cfg = env, cfg
        self.device = torch.device(env.device)
        self.num_envs, self.num_agents = env.num_envs, env.num_agents
        torch.manual_seed(seed)
        self.shared = bool(getattr(cfg, "shared", False))
        models = 1 if self.shared else self.num_agents
        self.agents = nn.ModuleList([
            AgentModels(env.obs_dim, env.critic_dim, cfg.actor_hidden, cfg.critic_hidden, cfg.init_std)
            for _ in range(models)]).to(self.device)
        self.optimizers = [make_optimizer(m, cfg.lr) for m in self.agents]
        self.lrs = [cfg.lr] * models
        self.storage = RolloutStorage(cfg.rollout, self.num_envs, self.num_agents, env.obs_dim, env.critic_dim,
                                      self.device)
        self.update_gen = torch.Generator().manual_seed(seed + 1)  # minibatch shuffles
        self.iteration = 0
        self.update_actor_norm = True  #: False keeps the actors' input statistics fixed (warm starts)
        self.precision = Precision("fp32", "fp32", "default")  #: of the PPO update (cfrace/rl/precision.py)
        self.update_workers = 1  #: threads the models' PPO updates run in (see _update); same weights either way
        self.loss_fn = None      #: the update's minibatch loss; None = eager (ippo.minibatch_loss), see use_compile
        self.env_steps = 0                                         # world transitions (E per step)
        self.total_reward = torch.zeros(self.num_agents, dtype=torch.float64)  # sum of r / E, per agent
        self.ep_return = torch.zeros(self.num_envs, self.num_agents, device=self.device)  # (E, A)
        self.fixed_opponents: list[AgentModels] = []                # see set_fixed_opponent
        self._not_fixed = None                                      # (E, A) bool: learner samples
        self._fixed_which = None                                    # (E,) long: which fixed opponent
        self.obs, self.critic = env.reset()                        # (E, A, D), (E, A, C)
        for a in range(self.num_agents):                            # warm start of the normalisers
            self.model(a).obs_norm.update(self.obs[:, a])
            self.model(a).critic_norm.update(self.critic[:, a])

    def model(self, agent: int) -> AgentModels:
        """The networks flying drone ``agent``."""
        return self.agents[0 if self.shared else agent]

    # ------------------------------------------------------------------ one iteration
    def iterate(self) -> dict[str, float]:
        """Rollout, GAE, one PPO update per model, normaliser update; the iteration's metrics."""
        t_start = time.perf_counter()
        cap = std_cap(self.cfg, self.iteration)
        for m in self.agents:   # the exploration-noise schedule (config.std_cap) of this iteration
            m.actor.std_max = cap
        roll = _RolloutSums(self.num_agents, self.device)
        for t in range(self.cfg.rollout):
            self._rollout_step(t, roll)
        t_update = time.perf_counter()
        metrics = self._update()
        _sync(self.device)
        t_end = time.perf_counter()
        self.iteration += 1
        steps = self.cfg.rollout * self.num_envs
        self.env_steps += steps
        self.total_reward += (roll.reward_sum / self.num_envs).double().cpu()
        metrics.update(self._rollout_metrics(roll, steps))
        total = t_end - t_start
        metrics.update(iteration=self.iteration, env_steps=self.env_steps, fps=steps / total, iter_s=total,
                       sim_s=roll.sim_s, infer_s=roll.infer_s, update_s=t_end - t_update)
        return metrics

    def _rollout_step(self, t: int, roll: "_RolloutSums") -> None:
        """Act, step the env, book the episode figures, bootstrap truncations, store step t."""
        t0 = time.perf_counter()
        actions, log_prob, values, mu, sigma = self._act(self.obs, self.critic)
        if self.fixed_opponents:
            fixed = ~self._not_fixed                                # (E, A)
            with torch.no_grad():
                for k, fo in enumerate(self.fixed_opponents):
                    mine = fixed & (self._fixed_which == k)[:, None]
                    actions[mine] = fo.actor(fo.obs_norm(self.obs[mine])).mean
        _sync(self.device)
        t1 = time.perf_counter()
        res = self.env.step(actions)
        _sync(self.device)
        t2 = time.perf_counter()
        alive = res.alive if self._not_fixed is None else res.alive & self._not_fixed
        reward = torch.where(alive, res.reward, 0.0)
        roll.book(self, res, alive, reward)
        # bootstrap on truncation: r_t += gamma V(s_final)
        boot = res.truncated & alive & ~res.terminated
        train_reward = reward.clone()
        if boot.any():
            t3 = time.perf_counter()
            for a in range(self.num_agents):
                ids = boot[:, a].nonzero().squeeze(-1)
                if len(ids):
                    train_reward[ids, a] += self.cfg.gamma * self.model(a).value(res.final_critic[ids, a])
            roll.infer_s += time.perf_counter() - t3
        self.storage.add(t, obs=self.obs, critic=self.critic, actions=actions, log_prob=log_prob, values=values,
                         mu=mu, sigma=sigma, rewards=train_reward, dones=res.terminated | res.truncated | ~alive,
                         alive=alive)
        self.obs, self.critic = res.obs, res.critic
        roll.infer_s += t1 - t0
        roll.sim_s += t2 - t1

    def _update(self) -> dict[str, float]:
        """GAE, then per model its PPO update and its normalisers' update; the update's metrics.

        With ``update_workers`` > 1 the models' updates run in that many threads at once (each
        model has its own networks, optimizer and samples; the shuffles are drawn beforehand in the
        sequential order), so the weights are the same as one after the other."""
        st = self.storage
        last_values = torch.stack([self.model(a).value(self.critic[:, a]) for a in range(self.num_agents)], 1)
        st.compute_returns(last_values, self.cfg.gamma, self.cfg.lam)
        metrics: dict[str, float] = {}
        drones = [[a] for a in range(self.num_agents)] if not self.shared else [list(range(self.num_agents))]
        batches = []
        for group in drones:
            parts = [st.agent_batch(a) for a in group]
            batches.append(parts[0] if len(parts) == 1 else {k: torch.cat([p[k] for p in parts]) for k in parts[0]})
        perms = [draw_perms(b["obs"].shape[0], self.cfg, self.update_gen) for b in batches]

        def update(k_model: int) -> tuple[dict, float]:
            return ppo_update(self.agents[k_model], self.optimizers[k_model], batches[k_model], self.cfg,
                              self.lrs[k_model], None, self.precision, perms[k_model], self.loss_fn)

        for k_model, (stats, lr) in enumerate(self._map(update, range(len(batches)))):
            self.lrs[k_model] = lr
            for k, v in stats.items():
                metrics[f"{k}_agent{k_model}"] = v
        for m, group in zip(self.agents, drones):
            alive_mask = st.alive[:, :, group]                      # (T, E, n)
            if self.update_actor_norm:
                m.obs_norm.update(st.obs[:, :, group][alive_mask])
            m.critic_norm.update(st.critic[:, :, group][alive_mask])
        return metrics

    def _map(self, fn, items) -> list:
        """[fn(x) for x in items], in update_workers threads when there are more than one (each thread
        with this thread's torch intra-op thread count)."""
        items = list(items)
        if self.update_workers <= 1 or len(items) <= 1:
            return [fn(x) for x in items]
        with ThreadPoolExecutor(min(self.update_workers, len(items)), initializer=torch.set_num_threads,
                                initargs=(torch.get_num_threads(),)) as pool:
            return list(pool.map(fn, items))

    def _rollout_metrics(self, roll: "_RolloutSums", steps: int) -> dict[str, float]:
        """Per drone: reward per alive step, mean episode return, total reward, lr, std, alive share;
        reward terms per alive step and the env's stats."""
        metrics: dict[str, float] = {}
        alive_count = self.storage.alive.sum((0, 1)).float()       # (A,)
        per_step = (roll.reward_sum / alive_count.clamp(min=1)).tolist()
        for a in range(self.num_agents):
            m = self.model(a)
            metrics[f"reward_agent{a}"] = per_step[a]
            metrics[f"return_agent{a}"] = float(np.mean(roll.returns[a])) if roll.returns[a] else float("nan")
            metrics[f"total_reward_agent{a}"] = float(self.total_reward[a])
            metrics[f"lr_agent{a}"] = self.lrs[0 if self.shared else a]
            metrics[f"std_agent{a}"] = float(m.actor.std().detach().mean())
            metrics[f"alive_agent{a}"] = float(alive_count[a]) / steps
        for name, value in roll.term_sums.items():
            for a, v in enumerate((value / alive_count.clamp(min=1)).tolist()):
                metrics[f"term_{name}_agent{a}"] = v
        for name, values in roll.stat_sums.items():
            metrics[f"stat_{name}"] = float(np.mean(values))
        return metrics

    @property
    def fixed_opponent(self) -> AgentModels | None:
        """The (first) frozen opponent, None without one."""
        return self.fixed_opponents[0] if self.fixed_opponents else None

    def set_fixed_opponent(self, models: AgentModels | list[AgentModels], fraction: float, drones: int = 1) -> int:
        """In the first round(fraction E) worlds the last ``drones`` agents' slots are flown by a
        frozen actor (its mean action), not by the learners: those samples are not the learners'
        (treated like dead steps: out of their GAE, losses and statistics). The other agents learn
        against it there and against each other elsewhere. Several ``models``: world i of those is
        flown by models[i % len(models)] (one per world). Returns the number of such worlds."""
        models = [models] if isinstance(models, AgentModels) else list(models)
        from cfrace.rl.inputs import check_fixed_drones
        check_fixed_drones(drones, self.num_agents)
        n = int(round(fraction * self.num_envs))
        mask = torch.ones(self.num_envs, self.num_agents, dtype=torch.bool, device=self.device)
        mask[:n, -drones:] = False
        self.fixed_opponents = [m.to(self.device).eval().requires_grad_(False) for m in models]
        self._not_fixed = mask
        self._fixed_which = torch.where(torch.arange(self.num_envs, device=self.device) < n,
                                        torch.arange(self.num_envs, device=self.device) % len(models), -1)
        return n

    def use_compile(self, on: bool, backend: str = "inductor") -> None:
        """Run the update's forward pass and losses through torch.compile (ippo.compiled_loss)."""
        self.loss_fn = compiled_loss(backend) if on else None

    def set_lr(self, lr: float) -> None:
        """Every agent's learning rate (the adaptive rule, if on, continues from it)."""
        self.lrs = [float(lr)] * len(self.agents)
        for o in self.optimizers:
            for g in o.param_groups:
                g["lr"] = float(lr)

    @torch.no_grad()
    def _act(self, obs: torch.Tensor, critic: torch.Tensor):
        """One forward pass per agent: sampled actions (E, A, 4), log-probs (E, A), values (E, A),
        Gaussian means and stds (E, A, 4)."""
        if self.shared:  # one pass over every drone of every world
            m = self.agents[0]
            dist = m.actor(m.obs_norm(obs))
            action = dist.sample()
            return (action, dist.log_prob(action).sum(-1), m.critic(m.critic_norm(critic)), dist.mean,
                    dist.stddev.expand_as(action))
        outs = []
        for a, m in enumerate(self.agents):
            dist = m.actor(m.obs_norm(obs[:, a]))
            action = dist.sample()
            outs.append((action, dist.log_prob(action).sum(-1), m.critic(m.critic_norm(critic[:, a])),
                         dist.mean, dist.stddev))
        return tuple(torch.stack(x, 1) for x in zip(*outs))

    # ------------------------------------------------------------------ state for checkpoints
    def state_dict(self) -> dict:
        env_state = self.env.state_dict() if hasattr(self.env, "state_dict") else None
        rng = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate(),
               "update": self.update_gen.get_state()}
        if self.device.type == "cuda":
            rng["cuda"] = torch.cuda.get_rng_state(self.device)
        return {"ippo": self.cfg.to_dict(), "iteration": self.iteration, "env_steps": self.env_steps,
                "agents": [m.state_dict() for m in self.agents],
                "optimizers": [o.state_dict() for o in self.optimizers], "lrs": list(self.lrs),
                "total_reward": self.total_reward.clone(), "rng": rng, "env_state": env_state,
                "obs": self.obs, "critic": self.critic, "ep_return": self.ep_return}

    def load_state_dict(self, state: dict) -> bool:
        """Restore everything. Returns True when the env state was restored too (exact resume);
        False when the env has no state_dict and was reset instead."""
        for m, s in zip(self.agents, state["agents"]):
            m.load_state_dict(s)
        for o, s in zip(self.optimizers, state["optimizers"]):
            o.load_state_dict(s)
        self.lrs = list(state["lrs"])
        for o, lr in zip(self.optimizers, self.lrs):
            for g in o.param_groups:
                g["lr"] = lr
        self.iteration, self.env_steps = int(state["iteration"]), int(state["env_steps"])
        self.total_reward = state["total_reward"].clone()
        rng = state["rng"]
        torch.set_rng_state(rng["torch"])
        np.random.set_state(rng["numpy"])
        random.setstate(rng["python"])
        self.update_gen.set_state(rng["update"])
        if "cuda" in rng and self.device.type == "cuda":
            torch.cuda.set_rng_state(rng["cuda"], self.device)
        exact = state.get("env_state") is not None and hasattr(self.env, "load_state_dict")
        if exact:
            self.env.load_state_dict(state["env_state"])
            self.obs, self.critic = state["obs"].to(self.device), state["critic"].to(self.device)
            self.ep_return = state["ep_return"].to(self.device)
        else:
            self.obs, self.critic = self.env.reset()
            self.ep_return.zero_()
        return exact
