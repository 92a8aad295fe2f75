"""Policy files for tests: tiny deterministic ONNX policies with valid metadata (no training)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx

from cfrace import __version__
from cfrace.contract import ACTION_DIM
from cfrace.drone import DEFAULT_PROFILE, load_profile
from cfrace.contract.actions import action_map_constants
from cfrace.contract.observations import LAYOUTS
from cfrace.policygraph import build_model


def make_test_policy(path: str | Path, layout_name: str, track: str, obstacles: bool, kind: str = "hover", *,
                     method: str | None = None, profile: str | None = None, seed: int = 0) -> Path:
    """Write a tiny deterministic ONNX policy with valid metadata (for tests).

    kind: "hover" (a0 = the hover value of the profile, zero rates), "zeros", "nan" (emits NaN),
    "random" (an ELU MLP [32, 32] with fixed random weights from ``seed``, plus a normaliser).
    method defaults to "ours" for multi-agent layouts and "ds" otherwise.
    """
    if layout_name not in LAYOUTS:
        raise ValueError(f"unknown layout {layout_name}")
    layout = LAYOUTS[layout_name]
    prof = load_profile(profile or DEFAULT_PROFILE)
    d = layout.dim
    meta = {"method": method or ("ours" if layout.opponent else "ds"), "track": getattr(track, "name", track),
            "obstacles": bool(obstacles), "obs_layout": layout.name, "obs_dim": d,
            **action_map_constants(prof), "policy_hz": 50.0, "drone_profile": prof.name,
            "train_steps": 0, "seed": int(seed), "cfrace_version": __version__, "agent": "ego", "test_kind": kind}
    zeros_w = np.zeros((ACTION_DIM, d), np.float32)
    mean = std = None
    if kind in ("hover", "nan"):
        hover = 2.0 / prof.max_thrust_weights - 1.0  # (a0 + 1) / 2 * T = 1 weight
        layers = [("linear", zeros_w, np.array([hover, 0, 0, 0], np.float32))]
    elif kind == "zeros":
        layers = [("linear", zeros_w, np.zeros(ACTION_DIM, np.float32))]
    elif kind == "random":
        gen = np.random.default_rng(seed)
        sizes = [d, 32, 32, ACTION_DIM]
        layers = []
        for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
            layers.append(("linear", (gen.normal(size=(b, a)) / np.sqrt(a)).astype(np.float32),
                           (0.1 * gen.normal(size=b)).astype(np.float32)))
            if i < len(sizes) - 2:
                layers.append(("elu", None, None))
        mean = gen.normal(size=d).astype(np.float32)
        std = (0.5 + gen.random(d)).astype(np.float32)
    else:
        raise ValueError(f"unknown test policy kind {kind!r} (hover, zeros, nan, random)")
    model = build_model(layers, mean, std, meta, d, nan_output=(kind == "nan"))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save_model(model, str(path))
    return path
