"""Warm start: initialise every agent's actor from a trained checkpoint (``cfrace train --init-from``).

Why: the paper trains the sparse competitive scheme from scratch with ~1.6e9 environment steps on a
large GPU. A 2-core CPU gets about 1e7 steps an hour, too few for flight to emerge from the sparse
reward alone. Starting both racers from a policy that already flies (e.g. the DS policy) keeps the
competitive, sparse objective of the training that follows, and the compute within reach. This is
a deviation from the paper, recorded in the checkpoint and in the exported ONNX metadata
(``init_from``), and documented in docs/training.md.

Observation layouts are prefixes of each other: solo36 is the first 36 entries of race42 (the
opponent block is appended at the end), solo39_obstacles the first 39 of race45_obstacles. The
first layer's weights for the extra inputs start at zero, so the warm-started actor initially acts
exactly like its source. Critics start fresh (their inputs and rewards differ).

The source may also be an exported policy file (.onnx, e.g. a shipped policy): its mean network
and observation normaliser are read back from the graph's weights (cfrace.policygraph names them);
the file carries no critic and no action std, so the actor's std is the preset's ``init_std``
(set it with ``--set init_std=...``) and ``--init-critic`` is refused.
"""

from __future__ import annotations

from pathlib import Path

import torch

from cfrace.contract.observations import LAYOUTS
from cfrace.errors import ConfigError
from cfrace.rl.checkpoint import load_checkpoint

OPP_POS_VAR = 4.0  #: m^2, prior variance of the opponent's body-frame position (std 2 m)
OPP_VEL_VAR = 9.0  #: (m/s)^2, prior variance of the opponent's velocity (std 3 m/s)


def onnx_actor_state(path: Path) -> tuple[dict, dict]:
    """(actor state dict in AgentModels' key names, metadata) of an exported policy file: the
    Gemm weights W{i}, b{i} (the mean network's Linear layers in order) and the normaliser
    norm_mean, norm_std (var = std^2 - NORM_EPS) of cfrace.policygraph.build_model."""
    import onnx
    from onnx import numpy_helper

    from cfrace.contract import NORM_EPS
    from cfrace.policy import OnnxPolicy

    meta = OnnxPolicy(path).meta
    inits = {t.name: torch.from_numpy(numpy_helper.to_array(t).copy())
             for t in onnx.load(str(path)).graph.initializer}
    linears = sorted((int(k[1:]) for k in inits if k[0] == "W" and k[1:].isdigit()))
    if not linears or "norm_mean" not in inits:
        raise ConfigError(f"--init-from {path}: not a cfrace policy graph (no W0 / norm_mean weights)")
    state = {}
    for k, i in enumerate(linears):   # Linear layers sit at 0, 2, 4, ... of mean_net (ELU between)
        state[f"actor.mean_net.{2 * k}.weight"] = inits[f"W{i}"]
        state[f"actor.mean_net.{2 * k}.bias"] = inits[f"b{i}"]
    std = inits["norm_std"].double()
    state["obs_norm.mean"] = inits["norm_mean"].double()
    state["obs_norm.var"] = (std * std - NORM_EPS).clamp_min(0.0)
    state["obs_norm.count"] = torch.tensor(1.0e6, dtype=torch.float64)
    return state, meta


def warm_start(runner, source: str | Path, env_layout: str | None, critic: bool = False) -> dict:
    """Copy the best source actor (greatest total training reward) into every agent of ``runner``;
    with ``critic`` also its critic and critic normaliser (see _copy_critic). Returns a description
    for the metadata. ``source``: a run folder, a checkpoint, or an exported .onnx policy."""
    path = Path(source)
    if path.is_dir():
        path = path / "checkpoint.pt"
    check_source(path, None, env_layout, critic)
    if path.suffix == ".onnx":
        src, meta = onnx_actor_state(path)
        saved, state, best = {"meta": meta}, {"env_steps": meta.get("train_steps", 0)}, 0
    else:
        saved = load_checkpoint(path)
        state = saved["runner"]
        totals = state["total_reward"]
        best = int(torch.argmax(totals)) if len(totals) > 1 else 0
        src = state["agents"][min(best, len(state["agents"]) - 1)]   # a shared run keeps one model
    src_layout = saved.get("meta", {}).get("obs_layout")
    added_position = False
    check_source(source, src_layout, env_layout)
    if src_layout and env_layout and src_layout != env_layout:
        a, b = LAYOUTS[src_layout], LAYOUTS[env_layout]
        if b.world_position and not a.world_position:   # a policy of the track without obstacles
            track = getattr(getattr(runner, "env", None), "track", None)
            src = with_world_position(src, a.dim, *position_prior(track))
            added_position = True
    for agent in runner.agents:
        dst = agent.state_dict()
        if critic:
            # the racer's critic reads [own observation, opponent's observation, other drones'...]:
            # one block per drone (two in a two-drone race)
            env = getattr(runner, "env", None)
            blocks = max(2, int(getattr(env, "num_agents", 2)))
            _transplant(src, dst, "critic", blocks=blocks, what=f"--init-critic: the critic of {source}")
        # Copied statistics keep their count: letting them drift made the frozen actors fly
        # differently, crash more, and drift further. New inputs (the opponent block) start from a
        # prior instead of the first reset batch (drones side by side: tiny variance, inputs clipped
        # at +-10 in flight).
        _transplant(src, dst, "actor", blocks=1, what=f"--init-from {source}: the actor")
        agent.load_state_dict(dst)
    return {"init_from": str(path), "init_agent": best, "init_env_steps": int(state.get("env_steps", 0)),
            "init_critic": bool(critic), **({"init_layout": src_layout} if added_position else {})}


def check_source(source, src_layout: str | None, env_layout: str | None, critic: bool = False,
                 option: str = "--init-from") -> None:
    """ConfigError (one line) unless ``source`` can start a run of ``env_layout``: an exported policy
    has no critic to copy, and a layout fits into another only by gaining inputs (the opponent block,
    the world position), never by losing them. warm_start applies it, and check_inputs before the banner."""
    if critic and Path(source).suffix == ".onnx":
        raise ConfigError(f"--init-critic: {source} is an exported policy and has no critic")
    if src_layout and env_layout and src_layout != env_layout:
        a, b = LAYOUTS[src_layout], LAYOUTS[env_layout]
        if (a.world_position and not b.world_position) or (a.opponent and not b.opponent):
            raise ConfigError(f"{option} {source}: layout {src_layout} does not fit into {env_layout}")


def position_prior(track) -> tuple[torch.Tensor, torch.Tensor]:
    """Normaliser statistics (mean (3,), var (3,)) for world-position inputs a source never read:
    the arena's centre and the variance of a uniform position over it (m, m^2)."""
    if track is None:
        return torch.zeros(3, dtype=torch.float64), torch.full((3,), OPP_POS_VAR, dtype=torch.float64)
    a = track.arena
    lo = torch.tensor([a.x[0], a.y[0], 0.0], dtype=torch.float64)
    hi = torch.tensor([a.x[1], a.y[1], a.z_max], dtype=torch.float64)
    return (lo + hi) / 2.0, (hi - lo) ** 2 / 12.0


def with_world_position(src: dict, block: int, mean: torch.Tensor, var: torch.Tensor) -> dict:
    """The source state (actor and, if present, critic) as if each of its observation blocks of
    ``block`` inputs had read the world position (3) first, as the obstacle layouts do: zero weights
    for it in the first layer (the network acts exactly as before) and the prior ``mean``/``var``
    in the normaliser. Other keys unchanged."""
    out = dict(src)
    for net, norm in (("actor", "obs_norm."), ("critic", "critic_norm.")):
        first = next((k for k in src if k.startswith(net + ".") and k.endswith("weight")), None)
        if first is None:
            continue
        w = src[first]
        n = w.shape[1] // block
        if n * block != w.shape[1]:
            raise ConfigError(f"--init-from: {first} reads {w.shape[1]} inputs, not blocks of {block}")
        out[first] = torch.cat([torch.cat([w.new_zeros(w.shape[0], 3), w[:, b * block:(b + 1) * block]], 1)
                                for b in range(n)], 1)
        for key, prior in (("mean", mean), ("var", var)):
            v = src[norm + key]
            out[norm + key] = torch.cat([torch.cat([prior.to(v.dtype), v[b * block:(b + 1) * block]])
                                         for b in range(n)])
    return out


def _transplant(src: dict, dst: dict, net: str, blocks: int, what: str) -> None:
    """Copy the source's ``net`` ("actor" or "critic") and its normaliser into the state dict
    ``dst`` (in place). Hidden sizes must be equal; the input may be wider: ``blocks`` observations
    side by side (1 for an actor, 2 for a racer's critic), each a source observation plus extra
    inputs (the opponent block). The first layer reads the first block's shared part with the
    source weights; every other input starts at weight zero, so the copy first acts (or predicts)
    exactly like its source. The normaliser takes the source statistics
    for every block's shared part and the opponent-block prior (mean 0, OPP_POS_VAR / OPP_VEL_VAR)
    for the rest.

    Why the critic too (--init-critic): warm-started DS fine-tuning held 100 % success with the
    source critic and fell to 0 % with a fresh one (docs/training.md, warm start item 5)."""
    norm = "obs_norm." if net == "actor" else "critic_norm."
    first = next(k for k in src if k.startswith(net + ".") and k.endswith("weight"))
    for key, value in src.items():
        if not key.startswith((net + ".", norm)):
            continue
        if key not in dst:
            raise ConfigError(f"{what} does not fit ({key} does not exist here)")
        target = dst[key]
        if target.shape == value.shape:
            target.copy_(value)
        elif key == first and target.shape[0] == value.shape[0] and (
                target.shape[1] >= blocks * value.shape[1] or 2 * target.shape[1] == blocks * value.shape[1]):
            target.zero_()
            target[:, : value.shape[1]] = value
        elif key in (norm + "mean", norm + "var") and 2 * target.shape[0] == blocks * value.shape[0] and blocks > 2:
            # a two-drone critic's statistics [own, opponent] into an N-drone critic's: the extra
            # drones' blocks take the opponent's
            size = value.shape[0] // 2
            target[: 2 * size] = value
            for b in range(2, blocks):
                target[b * size: (b + 1) * size] = value[size:]
        elif key in (norm + "mean", norm + "var") and target.shape[0] >= blocks * value.shape[0]:
            size, n = target.shape[0] // blocks, value.shape[0]
            prior = torch.tensor([OPP_POS_VAR] * 3 + [OPP_VEL_VAR] * 3, dtype=target.dtype)
            fill = torch.zeros_like(prior) if key.endswith("mean") else prior
            for b in range(blocks):
                target[b * size: b * size + n] = value
                if size > n:
                    target[b * size + n: (b + 1) * size] = fill[-(size - n):]
        else:
            raise ConfigError(f"{what} does not fit ({key}: {tuple(value.shape)} there, "
                              f"{tuple(target.shape)} here; different network sizes)")
