"""Rotations of unit quaternions (w, x, y, z) as numpy matrices: the one definition that the flight
stack's estimator and the simulated Crazyflie's firmware both use."""

from __future__ import annotations

import numpy as np


def quat_to_rot(q) -> np.ndarray:
    """Unit quaternion (4,) w, x, y, z -> rotation matrix (3, 3) (same frames as the quaternion)."""
    w, x, y, z = (float(v) for v in q)
    return rot_wxyz(w, x, y, z)


def rot_wxyz(w: float, x: float, y: float, z: float) -> np.ndarray:
    """The rotation matrix (3, 3) of a unit quaternion, from one flat list (a third of the cost of nested rows)."""
    return np.array([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]).reshape(3, 3)
