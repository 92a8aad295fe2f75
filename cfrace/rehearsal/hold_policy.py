"""Hand-made linear ONNX policies that really fly (for flight-stack tests and demos without
trained policies): take off, level, hold the current target gate's height and, with seek > 0,
drift towards the target gate's centre. Linear in the training observation, so it is one Gemm
layer written by cfrace.policygraph.build_model with valid metadata; it does NOT race well (a trained
policy does), it only gives the flight stack a drone in the air.

Observation entries used (layout without world position; +3 with it):
    v_body (0..2), R row-major (3..11), current gate corners in body frame (12..23).
Control (small angles, body yaw held): thrust a0 = hover + kz * (mean corner z) - kvz * v_z;
desired tilt from the gate centre's body-frame offset and the velocity; rates = k_att * angle error.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import onnx

from cfrace import __version__
from cfrace.drone import GRAVITY, load_profile
from cfrace.contract.actions import action_map_constants
from cfrace.contract.observations import LAYOUTS
from cfrace.policygraph import build_model


def hold_policy_layers(layout, max_thrust_weights: float, max_rates_deg, *, seek: float = 0.0,
                       height_offset: float = 0.0, through: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(W (4, D), b (4,)) of the linear controller for ``layout`` (cfrace.contract.observations.ObsLayout).

    With seek > 0 the horizontal target is the point ``through`` m beyond the target gate's centre
    along -n (n from the corners: y_gate = c0 - c1 for a 1 m opening, n = y_gate x z, z ~ body z),
    so the drone flies through the gate instead of stopping in it."""
    d = layout.dim
    o = 3 if layout.world_position else 0
    vx, vy, vz = o + 0, o + 1, o + 2

    def r(i, j):
        return o + 3 + 3 * i + j

    corner = [[o + 12 + 3 * c + k for k in range(3)] for c in range(4)]
    w = np.zeros((4, d), np.float64)
    b = np.zeros(4, np.float64)
    a_per_weight = 2.0 / max_thrust_weights          # a0 units per weight of thrust
    kp_z, kd_z = 4.0, 3.0                            # 1/s^2, 1/s
    b[0] = a_per_weight - 1.0 + a_per_weight * kp_z * height_offset / GRAVITY
    for c in range(4):
        w[0, corner[c][2]] += a_per_weight * kp_z / GRAVITY / 4.0
    w[0, vz] -= a_per_weight * kd_z / GRAVITY
    k_att = 6.0                                     # 1/s, angle error -> rate
    k_pos, k_vel = 0.08 * seek, 0.25                 # rad per m, rad per m/s
    rate_scale = [math.radians(v) for v in max_rates_deg]
    # target point in body frame, linear in the corners: tx = mean cx - a n_x, ty = mean cy - a n_y
    # with n_x = c0y - c1y, n_y = -(c0x - c1x)
    tx = np.zeros(d)
    ty = np.zeros(d)
    for c in range(4):
        tx[corner[c][0]] += 0.25
        ty[corner[c][1]] += 0.25
    tx[corner[0][1]] -= through
    tx[corner[1][1]] += through
    ty[corner[0][0]] += through
    ty[corner[1][0]] -= through
    # pitch (about +y, nose down +) accelerates +x: theta_d = k_pos tx - k_vel vx; theta ~ -R20
    w[2] += k_att * k_pos * tx / rate_scale[1]
    w[2, vx] -= k_att * k_vel / rate_scale[1]
    w[2, r(2, 0)] += k_att / rate_scale[1]
    # roll (about +x) accelerates -y: phi_d = -(k_pos ty - k_vel vy); phi ~ R21
    w[1] -= k_att * k_pos * ty / rate_scale[0]
    w[1, vy] += k_att * k_vel / rate_scale[0]
    w[1, r(2, 1)] -= k_att / rate_scale[0]
    return w.astype(np.float32), b.astype(np.float32)


def make_hold_policy(path: str | Path, layout_name: str, track: str, obstacles: bool, *, seek: float = 0.0,
                     method: str | None = None, profile: str = "cf2x_paper", height_offset: float = 0.0) -> Path:
    """Write the linear take-off-and-hold policy as an ONNX file with valid cfrace metadata."""
    layout = LAYOUTS[layout_name]
    prof = load_profile(profile)
    consts = action_map_constants(prof)
    w, b = hold_policy_layers(layout, consts["max_thrust_weights"], consts["max_rates_deg"], seek=seek,
                              height_offset=height_offset)
    meta = {"method": method or ("ours" if layout.opponent else "ds"), "track": getattr(track, "name", track),
            "obstacles": bool(obstacles), "obs_layout": layout.name, "obs_dim": layout.dim, **consts,
            "policy_hz": 50.0, "drone_profile": prof.name, "train_steps": 0, "seed": 0,
            "cfrace_version": __version__, "test_kind": f"hold(seek={seek})"}
    model = build_model([("linear", w, b)], None, None, meta, layout.dim)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save_model(model, str(path))
    return path


def make_sized_hold_policy(path: str | Path, layout_name: str, track: str, obstacles: bool, *,
                           hidden=(512, 512, 256, 128), seek: float = 0.0, seed: int = 0,
                           profile: str = "cf2x_paper") -> Path:
    """The hold controller inside an MLP of the paper's actor size (dense random weights that do
    not reach the output), so inference costs what a trained actor costs: ReLU pairs carry the
    4 controller outputs through, relu(h) - relu(-h) = h, for `cfrace bench loop`."""
    layout = LAYOUTS[layout_name]
    prof = load_profile(profile)
    consts = action_map_constants(prof)
    w_lin, b_lin = hold_policy_layers(layout, consts["max_thrust_weights"], consts["max_rates_deg"], seek=seek)
    rng = np.random.default_rng(seed)
    layers, size_in = [], layout.dim
    for j, h in enumerate(hidden):
        w = (rng.normal(size=(h, size_in)) / np.sqrt(size_in)).astype(np.float32)
        b = np.zeros(h, np.float32)
        if j == 0:
            w[:4], w[4:8], b[:4], b[4:8] = w_lin, -w_lin, b_lin, -b_lin
        else:
            w[:8] = 0.0
            w[:, :8] = 0.0
            w[:8, :8] = np.eye(8, dtype=np.float32)
        layers += [("linear", w, b), ("relu", None, None)]
        size_in = h
    w_out = np.zeros((4, size_in), np.float32)
    w_out[:, :4], w_out[:, 4:8] = np.eye(4), -np.eye(4)
    layers.append(("linear", w_out, np.zeros(4, np.float32)))
    meta = {"method": "ours" if layout.opponent else "ds", "track": getattr(track, "name", track),
            "obstacles": bool(obstacles), "obs_layout": layout.name, "obs_dim": layout.dim, **consts,
            "policy_hz": 50.0, "drone_profile": prof.name, "train_steps": 0, "seed": seed,
            "cfrace_version": __version__, "test_kind": f"hold(seek={seek}) in {list(hidden)}"}
    model = build_model(layers, None, None, meta, layout.dim)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save_model(model, str(path))
    return path
