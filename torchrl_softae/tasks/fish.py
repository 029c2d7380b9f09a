"""Tasks of the fish (Table S5): (iii) ``forward``, (iv) ``backward`` on ``SoftFish-v0``;
(v) ``to-target``, (vi) ``from-target`` on ``SoftFishTarget-v0`` (the state starts with the
target's position relative to the head)."""
from __future__ import annotations

from torchrl_softae.tasks.base import Task

__all__ = ["tasks"]


def tasks(with_target: bool = False) -> dict[str, Task]:
    if with_target:
        return {
            "to-target": Task("to-target", lambda s, a, s2: -s2[..., 0:3].norm(dim=-1), 200, None,
                              "(v) swim to the target: -||p - p_target||"),
            "from-target": Task("from-target", lambda s, a, s2: s2[..., 0:3].norm(dim=-1), 200, None,
                                "(vi) swim away from the target: +||p - p_target||"),
        }
    return {
        "forward": Task("forward", lambda s, a, s2: s2[..., 0], 200, None, "(iii) swim along +x: v_x"),
        "backward": Task("backward", lambda s, a, s2: -s2[..., 0], 200, None, "(iv) turn and swim along -x: -v_x"),
    }
