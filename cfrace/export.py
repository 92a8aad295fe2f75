"""Actor (+ its observation normaliser) -> ONNX with metadata, parity-checked.

The graph is written by hand with ``onnx.helper`` (no tracing, no exporter dependency), opset 17:

    obs [batch, D] float32
      -> (obs - mean) / sqrt(var + eps), clipped to +-10     (the training normaliser, folded in)
      -> Gemm -> ELU -> ... -> Gemm                          (the actor's mean network)
      -> clip(-1, 1)                                         (evaluation uses the mean action)
    action [batch, 4] float32

Metadata (the policy contract, cfrace.contract) is stored as ONNX metadata_props: strings as they
are, every other value as JSON. ``cfrace.policy.OnnxPolicy`` reads it back and validates it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import torch

from cfrace import __version__
from cfrace.contract import ACTION_DIM, META_SCHEMA, NORM_CLIP, NORM_EPS, validate_meta
from cfrace.errors import PolicyError
from cfrace.policy import OnnxPolicy
from cfrace.policygraph import Layer, build_model
from cfrace.rl.checkpoint import load_checkpoint
from cfrace.rl.config import IPPOConfig, preset
from cfrace.rl.models import AgentModels

def module_layers(actor: torch.nn.Module) -> list[Layer]:
    """The mean network of an actor as a layer list. Accepts an nn.Sequential of Linear/ELU/ReLU/
    Tanh/Identity, or any module with such a Sequential as ``mean_net``."""
    net = getattr(actor, "mean_net", actor)
    if not isinstance(net, torch.nn.Sequential):
        raise TypeError(f"cannot export {type(actor).__name__}: expected nn.Sequential or .mean_net")
    layers: list[Layer] = []
    for m in net:
        if isinstance(m, torch.nn.Linear):
            w = m.weight.detach().cpu().float().numpy()
            b = m.bias.detach().cpu().float().numpy() if m.bias is not None else np.zeros(w.shape[0], np.float32)
            layers.append(("linear", w, b))
        elif isinstance(m, torch.nn.ELU):
            if m.alpha != 1.0:
                raise TypeError("only ELU(alpha=1) is exported")
            layers.append(("elu", None, None))
        elif isinstance(m, torch.nn.ReLU):
            layers.append(("relu", None, None))
        elif isinstance(m, torch.nn.Tanh):
            layers.append(("tanh", None, None))
        elif not isinstance(m, torch.nn.Identity):
            raise TypeError(f"cannot export layer {type(m).__name__}")
    return layers


def norm_arrays(normalizer) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(mean, std) float32 arrays from (mean, var) tensors, an object with .mean/.var, or None.
    std = sqrt(var + NORM_EPS), computed in float32 exactly like the training forward pass."""
    if normalizer is None:
        return None, None
    mean, var = (normalizer.mean, normalizer.var) if hasattr(normalizer, "var") else normalizer
    mean = torch.as_tensor(mean).detach().cpu().float()
    std = torch.sqrt(torch.as_tensor(var).detach().cpu().float() + NORM_EPS)
    return mean.numpy(), std.numpy()


def export_actor(actor_module: torch.nn.Module, normalizer, meta: dict, path: str | Path) -> Path:
    """Write the actor (mean action, clipped to [-1, 1]) with its normaliser and metadata to ONNX.

    normalizer: (mean (D,), var (D,)) tensors, an object with .mean/.var, or None.
    meta: the contract keys (see META_SCHEMA); extra keys (e.g. agent) are kept.
    """
    path = Path(path)
    meta = validate_meta(dict(meta), str(path))
    layers = module_layers(actor_module)
    linears = [layer for layer in layers if layer[0] == "linear"]
    if not linears:
        raise TypeError("actor has no Linear layer")
    in_dim, out_dim = linears[0][1].shape[1], linears[-1][1].shape[0]
    if in_dim != meta["obs_dim"] or out_dim != ACTION_DIM:
        raise PolicyError(f"{path}: actor maps {in_dim} -> {out_dim}, metadata says obs_dim {meta['obs_dim']} -> 4")
    mean, std = norm_arrays(normalizer)
    if mean is not None and mean.shape != (in_dim,):
        raise PolicyError(f"{path}: normaliser has shape {mean.shape}, actor input is {in_dim}")
    model = build_model(layers, mean, std, meta, in_dim)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    onnx.save_model(model, str(tmp))
    tmp.replace(path)
    return path


@torch.no_grad()
def torch_reference(actor_module: torch.nn.Module, normalizer, obs: torch.Tensor) -> torch.Tensor:
    """What the exported graph computes, in torch: clip(mean_net(clip((obs - m) / s, +-10)), -1, 1)."""
    net = getattr(actor_module, "mean_net", actor_module)
    x = obs.float()
    if normalizer is not None:
        mean, std = (torch.from_numpy(a) for a in norm_arrays(normalizer))
        x = ((x - mean) / std).clamp(-NORM_CLIP, NORM_CLIP)
    return net(x).clamp(-1.0, 1.0)


def parity_check(path: str | Path, actor_module: torch.nn.Module, normalizer, n: int = 1000,
                 seed: int = 0, obs: np.ndarray | None = None) -> float:
    """Max |onnxruntime - torch| over ``n`` observations (random around the normaliser's statistics
    unless ``obs`` is given). Used by `cfrace export` and the tests."""
    policy = OnnxPolicy(path)
    if obs is None:
        gen = np.random.default_rng(seed)
        mean, std = norm_arrays(normalizer)
        d = policy.meta["obs_dim"]
        mean = np.zeros(d, np.float32) if mean is None else mean
        std = np.ones(d, np.float32) if std is None else std
        obs = (mean + std * gen.normal(size=(n, d)) * 2.0).astype(np.float32)
    ours = policy(obs)
    ref = torch_reference(actor_module, normalizer, torch.from_numpy(obs)).numpy()
    return float(np.abs(ours - ref).max())


AGENTS = ("ego", "adversary", "best")


def _source_name(path: str) -> str:
    """A warm start's or fixed opponent's name for the metadata: the run folder of a checkpoint,
    the file name of an exported policy."""
    p = Path(path)
    return p.name if p.suffix == ".onnx" else (p.parent.name or str(path))


def training_meta(ippo: IPPOConfig, multi_agent: bool) -> dict:
    """What a run set away from its preset that changes what it learns (docs/training.md, "Sparse
    from scratch"): the discount (--set gamma), the actor's initial action std
    and the schedule of its cap (--set init_std / std_final, config.std_cap); nothing for the defaults."""
    out = {"init_std": float(ippo.init_std)} if ippo.init_std != IPPOConfig.init_std else {}
    if ippo.std_final is not None:
        out.update(std_final=float(ippo.std_final), std_anneal_iters=int(ippo.std_anneal_iters))
    if ippo.gamma != preset(ippo.preset, multi_agent).gamma:
        out["gamma"] = float(ippo.gamma)
    return out


def export_checkpoint(checkpoint: str | Path, path: str | Path, agent: str = "best") -> tuple[Path, dict, float]:
    """Export one actor of a training checkpoint (cfrace/rl/train.py) to ONNX, then check parity.

    agent: "ego" (agent 0), "adversary" (agent 1), or "best": the agent with the greater total
    training reward (paper Sec. IV). Returns (path, metadata, max |onnx - torch| on 1000 obs).
    """
    if agent not in AGENTS:
        raise PolicyError(f"unknown agent {agent!r} (choose from {', '.join(AGENTS)})")
    ckpt = load_checkpoint(checkpoint)
    state, meta0 = ckpt["runner"], dict(ckpt["meta"])
    totals = [float(v) for v in state["total_reward"]]
    n = len(state["agents"])
    if agent == "best":
        index = max(range(n), key=lambda i: totals[i])
    else:
        index = AGENTS.index(agent)
        if index >= n:
            raise PolicyError(f"{checkpoint}: single-agent checkpoint has no {agent}; use --agent ego or best")
    if meta0.get("obs_layout") is None:
        raise PolicyError(f"{checkpoint}: checkpoint has no observation layout (trained on a toy env?)")
    ippo = IPPOConfig.from_dict(state["ippo"])
    model = AgentModels(meta0["obs_dim"], meta0["critic_dim"], ippo.actor_hidden, ippo.critic_hidden, ippo.init_std)
    model.load_state_dict(state["agents"][min(index, len(state["agents"]) - 1)])   # shared: one model
    meta = {k: meta0[k] for k in META_SCHEMA if k in meta0}
    meta.update(train_steps=int(state["env_steps"]), cfrace_version=__version__,
                agent=(AGENTS[index] if index < 2 else f"drone{index}") if n > 1 else "ego", agent_index=index,
                num_agents=n,
                total_training_reward=totals[index], iterations=int(state["iteration"]),
                preset=ippo.preset)
    if meta0.get("init_from"):  # warm-started (cfrace/rl/warmstart.py): say from what
        meta["init_from"] = _source_name(meta0["init_from"])
        meta["init_env_steps"] = int(meta0.get("init_env_steps", 0))
    if meta0.get("fixed_opponent"):  # trained partly against a frozen actor (--fixed-opponent)
        meta["fixed_opponent"] = ",".join(_source_name(s) for s in str(meta0["fixed_opponent"]).split(","))
        meta["fixed_opponent_worlds"] = int(meta0.get("fixed_opponent_worlds", 0))
        if meta0.get("fixed_opponent_drones"):  # it flew more than the last drone (--fixed-opponent-drones)
            meta["fixed_opponent_drones"] = int(meta0["fixed_opponent_drones"])
    if meta0.get("opponent_rule"):  # trained in fields of more than two drones (--drones N)
        meta["opponent_rule"] = str(meta0["opponent_rule"])
    if meta0.get("flight_obs"):  # trained on the flight stack's velocity estimate (--flight-obs)
        meta["flight_obs"] = True
    for key in ("ground_start_prob", "parked_opponent_frac"):  # start mix, races with the opponent down (options)
        if meta0.get(key) is not None:
            meta[key] = float(meta0[key])
    if meta0.get("loop"):  # trained through the lab loop's model (--lab-loop, cfrace/loopmodel.py)
        meta["loop"] = dict(meta0["loop"])
    if meta0.get("drone_ranges"):  # drone-model ranges spanning other profiles (--span-profiles)
        meta["drone_ranges"] = dict(meta0["drone_ranges"])
    meta.update(training_meta(ippo, int(meta0.get("num_agents", n)) >= 2))
    if meta0.get("obstacle_curriculum"):  # obstacles grown over the first iterations (--obstacle-curriculum)
        meta["obstacle_curriculum"] = int(meta0["obstacle_curriculum"])
    if meta0.get("rewards"):  # reward weights other than the paper's (--reward)
        meta["rewards"] = {str(k): float(v) for k, v in dict(meta0["rewards"]).items()}
    if meta0.get("init_layout"):  # warm-started from another observation layout (world position added)
        meta["init_layout"] = str(meta0["init_layout"])
    out = export_actor(model.actor, model.obs_norm, meta, path)
    err = parity_check(out, model.actor, model.obs_norm, n=1000)
    if not err < 1e-4:
        raise PolicyError(f"{out}: exported actor differs from torch by {err:.2e} (parity check failed)")
    return out, meta, err
