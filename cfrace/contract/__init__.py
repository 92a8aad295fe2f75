"""The policy contract: what a policy file promises to every part of cfrace that reads or writes one.

A policy file is ONNX with one input "obs" [batch, obs_dim] float32 and one output "action"
[batch, ACTION_DIM] float32 in [-1, 1]; the observation normaliser (x - mean) / sqrt(var + NORM_EPS),
clipped to +-NORM_CLIP, is inside the graph; the metadata below sits in the ONNX metadata_props
(strings as they are, every other value as JSON).

Schema versions: 1 = files written before the key ``schema_version`` existed (the same keys as 2);
2 = ``schema_version`` written. A file with a newer version than SCHEMA_VERSION is refused with
one line. This module imports neither torch nor the trainer (export, policy loading, rewards and
the trainer import it).
"""

from __future__ import annotations

import json
import math

from cfrace.contract.observations import LAYOUTS
from cfrace.errors import PolicyError

SCHEMA_VERSION = 2    #: the metadata schema this cfrace writes (and the newest it reads)
ACTION_DIM = 4        #: [a0 collective thrust, a1 a2 a3 body rates], each in [-1, 1]
NORM_EPS = 1e-4       #: added to the running variance before the square root (std floor 0.01)
NORM_CLIP = 10.0      #: normalised observations are clipped to +-NORM_CLIP
POLICY_HZ = 50.0      #: Hz, the rate policies are trained and evaluated at (metadata policy_hz)
MAX_POLICY_HZ = 1000.0       #: Hz, the highest policy_hz a file may state (the loop runs at most 1 kHz)
MAX_THRUST_WEIGHTS = 10.0    #: the highest max_thrust_weights a file may state (a flight checks the profile's)
POLICY_DT = 1.0 / POLICY_HZ   #: s, one action holds this long (0.02)

METHODS = ("ours", "ds", "ss", "dm")      #: the paper's four reward schemes
MULTI_AGENT_METHODS = ("ours", "dm")      #: the schemes trained two drones per world

#: metadata key -> expected Python type after parsing (every policy file carries these)
META_SCHEMA: dict[str, type] = {
    "method": str, "track": str, "obstacles": bool, "obs_layout": str, "obs_dim": int,
    "max_thrust_weights": float, "max_rates_deg": list, "policy_hz": float, "drone_profile": str,
    "train_steps": int, "seed": int, "cfrace_version": str,
}


def encode_meta(meta: dict) -> dict[str, str]:
    """Metadata values -> strings (str unchanged, everything else JSON)."""
    return {str(k): v if isinstance(v, str) else json.dumps(v) for k, v in meta.items()}


def decode_meta(raw: dict[str, str]) -> dict:
    """ONNX metadata_props strings -> values (the inverse of encode_meta; JSON-less text stays text)."""
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


def schema_version(meta: dict) -> int:
    """The schema version of a metadata dict (1 when the key is absent)."""
    return meta.get("schema_version", 1)


def _check_version(meta: dict, where: str) -> None:
    version = schema_version(meta)
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise PolicyError(f"{where}: metadata schema_version={version!r} should be a positive integer")
    if version > SCHEMA_VERSION:
        raise PolicyError(f"{where}: written with policy schema {version}; this cfrace reads schemas 1-"
                          f"{SCHEMA_VERSION} (update cfrace to fly it)")


def _check_types(meta: dict, where: str) -> dict:
    missing = [k for k in META_SCHEMA if k not in meta]
    if missing:
        raise PolicyError(f"{where}: metadata is missing key(s) {', '.join(missing)}")
    out = dict(meta)
    for key, kind in META_SCHEMA.items():
        value = meta[key]
        if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
            out[key] = float(value)
        elif kind is int and isinstance(value, int) and not isinstance(value, bool):
            out[key] = int(value)
        elif not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            raise PolicyError(f"{where}: metadata {key}={value!r} should be {kind.__name__}")
    return out


def validate_meta(meta: dict, where: str) -> dict:
    """Check a parsed metadata dict against the contract; returns it normalised (float/int types).
    Raises PolicyError naming ``where`` and the first problem."""
    _check_version(meta, where)
    out = _check_types(meta, where)
    if out["method"] not in METHODS:
        raise PolicyError(f"{where}: metadata method={out['method']!r} is not one of {', '.join(METHODS)}")
    layout = LAYOUTS.get(out["obs_layout"])
    if layout is None:
        raise PolicyError(f"{where}: metadata obs_layout={out['obs_layout']!r} is unknown "
                          f"(known: {', '.join(LAYOUTS)})")
    if out["obs_dim"] != layout.dim:
        raise PolicyError(f"{where}: metadata obs_dim={out['obs_dim']} does not match obs_layout "
                          f"{layout.name} ({layout.dim})")
    if layout.opponent != (out["method"] in MULTI_AGENT_METHODS):
        raise PolicyError(f"{where}: obs_layout {layout.name} does not fit method {out['method']}")
    if layout.world_position != out["obstacles"]:
        raise PolicyError(f"{where}: obs_layout {layout.name} does not fit obstacles={out['obstacles']}")
    rates = out["max_rates_deg"]
    if len(rates) != 3 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < math.inf
                                  for v in rates):
        raise PolicyError(f"{where}: metadata max_rates_deg={rates!r} should be 3 finite positive numbers")
    out["max_rates_deg"] = [float(v) for v in rates]
    for key, hi in (("max_thrust_weights", MAX_THRUST_WEIGHTS), ("policy_hz", MAX_POLICY_HZ)):
        if not 0 < out[key] <= hi:   # False for NaN
            raise PolicyError(f"{where}: metadata {key}={out[key]!r} should be a number in (0, {hi:g}]")
    return out


def policy_filename(method: str, track_name: str, obstacles: bool) -> str:
    """The shipped file name of a policy: {method}_{track}[_obstacles].onnx."""
    return f"{method}_{track_name}{'_obstacles' if obstacles else ''}.onnx"
