"""numpy or torch: the array module of an argument, for code written once for both.

Rules shared by training (torch tensors, batched) and flight (numpy, one drone) are written once
against this; torch is never imported here unless a tensor came in (then it is loaded already).
"""

from __future__ import annotations

import numpy as np


def array_module(x):
    """numpy for numpy arrays (and scalars), torch for tensors."""
    if isinstance(x, (np.ndarray, np.generic, float, int)):
        return np
    import torch

    return torch
