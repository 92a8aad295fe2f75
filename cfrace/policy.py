"""ONNX racing policies: load, validate, run (onnxruntime, one thread, low latency).

A policy file (written by cfrace.export) has one input "obs" [batch, obs_dim] float32 and one
output "action" [batch, 4] float32 in [-1, 1]; its observation normaliser is inside the graph and
its metadata (method, track, obstacles, obs_layout, obs_dim, action map constants, ...) sits in the
ONNX metadata_props. Every problem is a one-line PolicyError naming the file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cfrace.errors import PolicyError
from cfrace.export import ACTION_DIM, META_SCHEMA, METHODS, build_model, validate_meta
from cfrace.paths import POLICIES_DIR

__all__ = ["OnnxPolicy", "resolve_policy", "make_test_policy", "policy_filename"]


def _decode_meta(raw: dict[str, str]) -> dict:
    meta = {}
    for key, text in raw.items():
        if META_SCHEMA.get(key) is str:
            meta[key] = text
            continue
        try:
            meta[key] = json.loads(text)
        except ValueError:
            meta[key] = text
    return meta


class OnnxPolicy:
    """A loaded policy. ``policy(obs (B, obs_dim) float32) -> actions (B, 4) float32``."""

    def __init__(self, path: str | Path):
        import onnxruntime as ort

        self.path = Path(path)
        where = str(self.path)
        if not self.path.exists():
            raise PolicyError(f"{where}: no such policy file")
        if not self.path.is_file():
            raise PolicyError(f"{where}: not a file")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.log_severity_level = 4  # errors are reported by us, in one line
        try:
            self.session = ort.InferenceSession(str(self.path), sess_options=opts,
                                                providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises several unrelated types for bad files
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise PolicyError(f"{where}: not a valid ONNX model ({first[:160]})") from None
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if [i.name for i in inputs] != ["obs"] or [o.name for o in outputs] != ["action"]:
            raise PolicyError(f"{where}: expected one input 'obs' and one output 'action', got inputs "
                              f"{[i.name for i in inputs]} and outputs {[o.name for o in outputs]}")
        ishape, oshape = inputs[0].shape, outputs[0].shape
        if len(ishape) != 2 or not isinstance(ishape[1], int):
            raise PolicyError(f"{where}: input 'obs' must be [batch, obs_dim], got {ishape}")
        if len(oshape) != 2 or oshape[1] != ACTION_DIM:
            raise PolicyError(f"{where}: output 'action' must be [batch, 4], got {oshape}")
        if inputs[0].type != "tensor(float)" or outputs[0].type != "tensor(float)":
            raise PolicyError(f"{where}: 'obs' and 'action' must be float32 tensors")
        self.meta: dict = validate_meta(_decode_meta(self.session.get_modelmeta().custom_metadata_map), where)
        if ishape[1] != self.meta["obs_dim"]:
            raise PolicyError(f"{where}: input 'obs' has {ishape[1]} values, metadata obs_dim is {self.meta['obs_dim']}")
        self.obs_dim: int = self.meta["obs_dim"]

    def check(self, track_name: str, obstacles: bool) -> None:
        """Raise PolicyError unless this policy was trained for ``track_name`` with/without obstacles."""
        name = getattr(track_name, "name", track_name)
        if self.meta["track"] != name:
            raise PolicyError(f"{self.path}: trained on track {self.meta['track']!r}, not {name!r}")
        if self.meta["obstacles"] != bool(obstacles):
            want = "with" if obstacles else "without"
            have = "with" if self.meta["obstacles"] else "without"
            raise PolicyError(f"{self.path}: trained {have} obstacles, but the race is {want} obstacles")

    def __call__(self, obs) -> np.ndarray:
        """obs (B, obs_dim) or (obs_dim,) -> actions (B, 4) or (4,), float32 in [-1, 1]."""
        x = np.ascontiguousarray(obs, dtype=np.float32)
        single = x.ndim == 1
        if single:
            x = x[None]
        if x.ndim != 2 or x.shape[1] != self.obs_dim:
            raise PolicyError(f"{self.path}: observation shape {tuple(np.shape(obs))}, expected (B, {self.obs_dim})")
        out = self.session.run(["action"], {"obs": x})[0]
        return out[0] if single else out

    def __repr__(self) -> str:
        m = self.meta
        return (f"OnnxPolicy({self.path.name}: {m['method']} on {m['track']}"
                f"{' with obstacles' if m['obstacles'] else ''}, {m['obs_layout']})")


def policy_filename(method: str, track_name: str, obstacles: bool) -> str:
    """The shipped file name of a policy: {method}_{track}[_obstacles].onnx."""
    return f"{method}_{track_name}{'_obstacles' if obstacles else ''}.onnx"


def resolve_policy(name_or_path: str | Path, track_name: str, obstacles: bool) -> Path:
    """Short names ours/ds/ss/dm -> policies/{name}_{track}[_obstacles].onnx; anything else is a
    path. Raises PolicyError when the file does not exist."""
    text = str(name_or_path)
    track_name = getattr(track_name, "name", track_name)
    if text in METHODS:
        path = POLICIES_DIR / policy_filename(text, track_name, obstacles)
        if not path.exists():
            have = ", ".join(sorted(p.name for p in POLICIES_DIR.glob("*.onnx"))) or "none"
            raise PolicyError(f"no shipped policy {path.name} in {POLICIES_DIR} (available: {have})")
        return path
    path = Path(text)
    if not path.exists():
        raise PolicyError(f"{path}: no such policy file")
    return path


def make_test_policy(path: str | Path, layout_name: str, track: str, obstacles: bool, kind: str = "hover", *,
                     method: str | None = None, profile: str | None = None, seed: int = 0) -> Path:
    """Write a tiny deterministic ONNX policy with valid metadata (for tests).

    kind: "hover" (a0 = the hover value of the profile, zero rates), "zeros", "nan" (emits NaN),
    "random" (an ELU MLP [32, 32] with fixed random weights from ``seed``, plus a normaliser).
    method defaults to "ours" for multi-agent layouts and "ds" otherwise.
    """
    from cfrace import __version__
    from cfrace.drone import DEFAULT_PROFILE, load_profile
    from cfrace.env.actions import action_map_constants
    from cfrace.env.observations import LAYOUTS

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
    import onnx

    model = build_model(layers, mean, std, meta, d, nan_output=(kind == "nan"))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save_model(model, str(path))
    return path
