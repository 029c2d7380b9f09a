"""The reaching reward of both arms (SoftArm, SoPrA) and their tasks (Table S5: a long-tailed shaped
function of the tip-to-target distance; its exact form is ours, the paper does not give it)."""
from __future__ import annotations

import numpy as np

__all__ = ["reach_reward"]


def reach_reward(distance, tolerance: float = 5e-3, scale: float = 0.02):
    """g(d) in (0, 1]: 1 within ``tolerance`` (5 mm), then a long (1/d) tail: 1 / (1 + (d - tol) / scale).

    Works on floats, numpy arrays and torch tensors alike.
    """
    excess = (distance - tolerance) / scale
    if hasattr(excess, "clamp"):
        excess = excess.clamp(min=0.0)
    else:
        excess = np.maximum(excess, 0.0)
    return 1.0 / (1.0 + excess)
