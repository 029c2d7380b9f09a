"""Tasks of dm_control's cartpole; observation = (cart x, cos phi, sin phi, x_dot, phi_dot)."""
from __future__ import annotations

from torchrl_softae.tasks.base import Task

__all__ = ["tasks"]


def tasks() -> dict[str, Task]:
    return {
        "swingup": Task("swingup", lambda s, a, s2: s2[..., 1] - 0.1 * s2[..., 0].square(), 200, None,
                        "pole up, cart near the centre"),
        "move-right": Task("move-right", lambda s, a, s2: s2[..., 3], 200, None, "drive the cart to the right"),
    }
