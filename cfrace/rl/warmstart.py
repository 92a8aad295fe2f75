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

NORM_COUNT_AFTER_WARM_START = 1.0e4  #: samples the copied normaliser statistics weigh


def warm_start(runner, source: str | Path, env_layout: str | None) -> dict:
    """Copy the best source actor (greatest total training reward) into every agent of ``runner``.
    Returns a description for the metadata."""
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
        # the copied sample count would freeze the statistics of the new inputs at their first
        # estimate (drones side by side at the start: tiny variance -> inputs clipped at +-10 in flight);
        # a small count lets every statistic follow the new data within a few iterations, while the
        # actors are frozen (critic warm-up)
        dst = agent.state_dict()
        dst["obs_norm.count"].clamp_(max=NORM_COUNT_AFTER_WARM_START)
        agent.load_state_dict(dst)
    return {"init_from": str(path), "init_agent": best, "init_env_steps": int(state.get("env_steps", 0))}
