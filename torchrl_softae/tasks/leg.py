"""Tasks of the musculoskeletal leg (Table S5): (vii) ``ccw`` and (viii) ``cw`` hopping around the boom
(state index 5 is the boom's yaw rate)."""
from __future__ import annotations

from torchrl_softae.tasks.base import Task

__all__ = ["tasks"]


def tasks() -> dict[str, Task]:
    return {
        "ccw": Task("ccw", lambda s, a, s2: s2[..., 5], 500, None, "(vii) hop counter-clockwise: +yaw rate"),
        "cw": Task("cw", lambda s, a, s2: -s2[..., 5], 500, None, "(viii) hop clockwise: -yaw rate"),
    }
