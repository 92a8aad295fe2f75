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
"""

from __future__ import annotations

from pathlib import Path

import torch

from cfrace.env.observations import LAYOUTS
from cfrace.errors import ConfigError

OPP_POS_VAR = 4.0  #: m^2, prior variance of the opponent's body-frame position (std 2 m)
OPP_VEL_VAR = 9.0  #: (m/s)^2, prior variance of the opponent's velocity (std 3 m/s)


def warm_start(runner, source: str | Path, env_layout: str | None, critic: bool = False) -> dict:
    """Copy the best source actor (greatest total training reward) into every agent of ``runner``;
    with ``critic`` also its critic and critic normaliser (see _copy_critic). Returns a description
    for the metadata."""
    from cfrace.rl.train import load_checkpoint

    path = Path(source)
    if path.is_dir():
        path = path / "checkpoint.pt"
    saved = load_checkpoint(path)
    state = saved["runner"]
    totals = state["total_reward"]
    best = int(torch.argmax(totals)) if len(totals) > 1 else 0
    src = state["agents"][best]
    src_layout = saved.get("meta", {}).get("obs_layout")
    if src_layout and env_layout and src_layout != env_layout:
        a, b = LAYOUTS[src_layout], LAYOUTS[env_layout]
        if a.world_position != b.world_position or (a.opponent and not b.opponent):
            raise ConfigError(f"--init-from {source}: layout {src_layout} is not a prefix of {env_layout}")
    for agent in runner.agents:
        dst = agent.state_dict()
        if critic:
            _copy_critic(src, dst, source)
        for key, value in src.items():
            if not (key.startswith("actor.") or key.startswith("obs_norm.")):
                continue
            if key not in dst:
                raise ConfigError(f"--init-from {source}: actor parameter {key} does not exist here")
            target = dst[key]
            if target.shape == value.shape:
                target.copy_(value)
            elif target.dim() == value.dim() and target.shape[:-1] == value.shape[:-1] and key.endswith("weight"):
                # first layer: (hidden, in) -> copy the shared inputs, zero the extra ones
                n = value.shape[-1]
                target.zero_()
                target[..., :n] = value
            elif target.dim() == 1 and value.dim() == 1 and key.startswith("obs_norm."):
                target[: value.shape[0]] = value
            else:
                raise ConfigError(f"--init-from {source}: {key} has shape {tuple(value.shape)}, "
                                  f"here {tuple(target.shape)} (different network sizes)")
        # new inputs (the opponent block): the copied sample count makes their statistics adapt slowly,
        # so start them from a sensible prior instead of the first reset batch (drones side by side:
        # tiny variance, inputs clipped at +-10 in flight). Copied statistics keep their count: letting
        # them drift made the frozen actors fly differently, crash more, and drift further.
        dim = dst["obs_norm.mean"].shape[0]
        n_src = src["obs_norm.mean"].shape[0]
        if dim > n_src:
            dst["obs_norm.mean"][n_src:] = 0.0
            prior = torch.tensor([OPP_POS_VAR] * 3 + [OPP_VEL_VAR] * 3, dtype=dst["obs_norm.var"].dtype)
            dst["obs_norm.var"][n_src:] = prior[-(dim - n_src):]
        agent.load_state_dict(dst)
    return {"init_from": str(path), "init_agent": best, "init_env_steps": int(state.get("env_steps", 0)),
            "init_critic": bool(critic)}


def _copy_critic(src: dict, dst: dict, source) -> None:
    """The source critic into ``dst`` (a state dict, modified in place), hidden sizes equal.

    Same input size: copied as it is. A single-agent source (input = its observation, D_s values)
    into a racer (input = [own observation, opponent's observation], 2 D values, D >= D_s): the first
    layer reads the own observation's first D_s values with the source weights, every other input
    starts at weight zero (so the critic first predicts what the source predicted); the normaliser
    takes the source statistics for both observations' shared part and the opponent-block prior
    for the rest. The features carry over; the warm-up (--critic-warmup) refits the values to the
    new reward. Measured on the lemniscate: warm-started DS fine-tuning held 100 % success with the
    source critic and fell to 0 % with a fresh one (docs/training.md)."""
    w_key = next(k for k in src if k.startswith("critic.") and k.endswith("weight"))
    for key, value in src.items():
        if not (key.startswith("critic.") or key.startswith("critic_norm.")):
            continue
        if key not in dst:
            raise ConfigError(f"--init-critic: the critic of {source} does not fit ({key} does not exist here)")
        target = dst[key]
        if target.shape == value.shape:
            target.copy_(value)
        elif key == w_key and target.shape[0] == value.shape[0] and target.shape[1] >= 2 * value.shape[1]:
            target.zero_()
            target[:, : value.shape[1]] = value
        elif key in ("critic_norm.mean", "critic_norm.var") and target.shape[0] >= 2 * value.shape[0]:
            half, n = target.shape[0] // 2, value.shape[0]
            prior = 0.0 if key.endswith("mean") else torch.tensor([OPP_POS_VAR] * 3 + [OPP_VEL_VAR] * 3,
                                                                 dtype=target.dtype)
            for start in (0, half):
                target[start:start + n] = value
                target[start + n:start + half] = prior if isinstance(prior, float) else prior[-(half - n):]
        else:
            raise ConfigError(f"--init-critic: the critic of {source} does not fit ({key}: "
                              f"{tuple(value.shape)} there, {tuple(target.shape)} here)")
