"""ONNX racing policies: load, validate, run (onnxruntime, one thread, low latency).

A policy file (written by cfrace.export; its contract, metadata schema and validation in
cfrace.contract) has one input "obs" [batch, obs_dim] float32 and one output "action" [batch, 4]
float32 in [-1, 1]. Every problem is a one-line PolicyError naming the file. No torch here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cfrace.contract import ACTION_DIM, METHODS, decode_meta, policy_filename, validate_meta
from cfrace.errors import PolicyError
from cfrace.paths import POLICIES_DIR

__all__ = ["OnnxPolicy", "resolve_policy", "policy_filename"]


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
        self.meta: dict = validate_meta(decode_meta(self.session.get_modelmeta().custom_metadata_map), where)
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
        raise PolicyError(f"{path}: no such policy file (short names: {', '.join(METHODS)}; else a path to an .onnx)")
    return path
