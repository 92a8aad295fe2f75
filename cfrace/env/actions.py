"""The action map, shared by the simulator/environment and the flight loop (no train/deploy skew).

A policy outputs a = [a0, a1, a2, a3] in [-1, 1]. Paper Sec. III-C:
    f_z = (a0 + 1) / 2 * T * m g        (collective thrust, N)
    omega_des = [k_x a1, k_y a2, k_z a3] (body rates, rad/s)
Works on torch tensors and numpy arrays alike (the last axis holds the four actions).
"""

from __future__ import annotations

import math

GRAVITY = 9.81


def action_map_constants(profile) -> dict:
    """The constants exported into ONNX metadata and used by the flight stack."""
    return {
        "max_thrust_weights": float(profile.max_thrust_weights),
        "max_rates_deg": [float(v) for v in profile.max_rates_deg],
    }


def action_to_command(action, mass: float, max_thrust_weights: float, max_rates_deg):
    """(..., 4) actions -> (thrust N (...,), rates rad/s (..., 3)). Actions are clipped to [-1, 1]."""
    a = action.clip(-1.0, 1.0)
    thrust = (a[..., 0] + 1.0) * 0.5 * (max_thrust_weights * mass * GRAVITY)
    k = [math.radians(v) for v in max_rates_deg]
    rates = a[..., 1:4] * _like(a, k)
    return thrust, rates


def _like(ref, values):
    try:
        import torch

        if isinstance(ref, torch.Tensor):
            return torch.tensor(values, dtype=ref.dtype, device=ref.device)
    except ImportError:  # pragma: no cover
        pass
    import numpy as np

    return np.asarray(values, dtype=ref.dtype)


#: thrust counts below which the Crazyflie firmware's legacy RPYT commander commands zero thrust
#: (MIN_THRUST, crtp_commander_rpyt.c); at zero thrust its controller resets (no rate control)
FIRMWARE_MIN_THRUST_COUNTS = 1000
