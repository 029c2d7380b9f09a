"""Input validation shared by the robot envs: bad input gets an error that names it."""
from __future__ import annotations

import numpy as np

__all__ = ["check_action"]


def check_action(owner: str, action, dim: int) -> np.ndarray:
    """``action`` as a float64 vector of ``dim`` finite values in [-1, 1], or a ValueError naming it."""
    a = np.asarray(action, dtype=np.float64).reshape(-1)
    if a.shape != (dim,):
        raise ValueError(f"{owner}: action has shape {a.shape}, expected ({dim},)")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{owner}: action contains NaN/inf: {a}")
    if np.any(np.abs(a) > 1 + 1e-6):
        raise ValueError(f"{owner}: action {a} is outside the action space [-1, 1]^{dim}")
    return a
