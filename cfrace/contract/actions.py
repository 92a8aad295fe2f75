"""The action map, shared by the simulator/environment and the flight loop (no train/deploy skew).

A policy outputs a = [a0, a1, a2, a3] in [-1, 1]. Paper Sec. III-C:
    f_z = (a0 + 1) / 2 * T * m g        (collective thrust, N)
    omega_des = [k_x a1, k_y a2, k_z a3] (body rates, rad/s)
and the flight stack sends f_z as CRTP thrust counts through the drone's calibration curve.

One definition in two forms: ``action_to_command`` for batches (torch tensors or numpy arrays, the
last axis holds the four actions; the environment and evaluation) and ``SetpointMap`` for one
drone per call on Python floats (the 100 Hz flight tick, where numpy's per-call overhead would
dominate). Both take their constants from ``thrust_scale``/``rate_gains`` and their thrust from
``collective_thrust``; ``thrust_to_counts`` and ``SetpointMap`` share the count limits.
tests/test_flight_core.py checks that the two forms give bit-identical setpoints.
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from cfrace.arrays import array_module
from cfrace.drone import GRAVITY

THRUST_MAX_COUNTS = 65535  #: uint16 thrust of the CRTP setpoint packet
#: thrust counts below which the Crazyflie firmware's legacy RPYT commander commands zero thrust
#: (MIN_THRUST, bitcraze/crazyflie-firmware src/modules/src/crtp_commander_rpyt.c); at zero thrust
#: its controller resets (no rate control)
FIRMWARE_MIN_THRUST_COUNTS = 1000


def action_map_constants(profile) -> dict:
    """The constants exported into ONNX metadata and used by the flight stack."""
    return {
        "max_thrust_weights": float(profile.max_thrust_weights),
        "max_rates_deg": [float(v) for v in profile.max_rates_deg],
    }


def thrust_scale(mass: float, max_thrust_weights: float) -> float:
    """N of collective thrust at a0 = 1: T m g."""
    return max_thrust_weights * mass * GRAVITY


def rate_gains(max_rates_deg) -> tuple[float, float, float]:
    """(k_x, k_y, k_z) rad/s of body rate at a = 1."""
    return tuple(math.radians(v) for v in max_rates_deg)


def collective_thrust(a0, scale: float):
    """a0 (a float or an array, already clipped to [-1, 1]) -> thrust N: (a0 + 1) / 2 * scale."""
    return (a0 + 1.0) * 0.5 * scale


def action_to_command(action, mass: float, max_thrust_weights: float, max_rates_deg):
    """(..., 4) actions -> (thrust N (...,), rates rad/s (..., 3)). Actions are clipped to [-1, 1]."""
    a = action.clip(-1.0, 1.0)
    thrust = collective_thrust(a[..., 0], thrust_scale(mass, max_thrust_weights))
    rates = a[..., 1:4] * _like(a, rate_gains(max_rates_deg))
    return thrust, rates


def _like(ref, values):
    """``values`` as an array of ref's kind, dtype (and device)."""
    xp = array_module(ref)
    if xp is np:
        return np.asarray(values, dtype=ref.dtype)
    return xp.tensor(values, dtype=ref.dtype, device=ref.device)


def thrust_to_counts(thrust_n, curve) -> np.ndarray | int:
    """Collective thrust (N) -> uint16 counts through the calibration curve (clamped, rounded)."""
    counts = np.clip(np.rint(curve.to_counts(thrust_n)), 0, THRUST_MAX_COUNTS)
    return int(counts) if np.ndim(counts) == 0 else counts.astype(np.int64)


class SetpointMap:
    """One drone's action (4,) -> (thrust N, body rates deg/s, thrust counts): action_to_command,
    np.degrees and thrust_to_counts with the same float64 operations in the same order on Python
    floats (bit-identical: tests/test_flight_core.py), a fraction of their cost on a 4-vector."""

    def __init__(self, mass: float, max_thrust_weights: float, max_rates_deg, curve):
        self.scale = thrust_scale(mass, max_thrust_weights)
        self.k = rate_gains(max_rates_deg)
        self.xp = [float(v) for v in curve.newtons]
        self.fp = [float(v) for v in curve.counts]

    def _interp(self, x: float) -> float:
        """np.interp(x, newtons, counts) for one finite x: numpy's rule and arithmetic
        (compiled_base.c: clamp at the ends, knot values exact, slope * (x - x_j) + y_j)."""
        xp, fp = self.xp, self.fp
        if x > xp[-1]:
            return fp[-1]
        if x < xp[0]:
            return fp[0]
        j = bisect.bisect_right(xp, x) - 1           # xp[j] <= x < xp[j + 1]
        if j == len(xp) - 1 or xp[j] == x:
            return fp[j]
        slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
        return slope * (x - xp[j]) + fp[j]

    def __call__(self, act) -> tuple[float, tuple[float, float, float], int]:
        """act: 4 numbers. Counts are 0 for a non-finite thrust (never sent: the safety check stops
        the drone)."""
        a0, a1, a2, a3 = (min(max(float(x), -1.0), 1.0) for x in act)   # NaN stays NaN, like clip
        thrust = collective_thrust(a0, self.scale)
        k = self.k
        rates = (math.degrees(a1 * k[0]), math.degrees(a2 * k[1]), math.degrees(a3 * k[2]))
        if not math.isfinite(thrust):
            return thrust, rates, 0
        c = round(self._interp(thrust))                             # round half to even, as np.rint
        return thrust, rates, min(max(c, 0), THRUST_MAX_COUNTS)
