"""Pipeline entry of the soft arm: tip x-z coverage, the held-out set and per-group accuracy.

``SoftArm-v0`` keeps its original held-out set (ramp rollouts toward settled tips of uniform random
actions). ``SoftArm-v1`` uses the paper's protocol: targets spread uniformly over the reachable
workspace volume, each reached by a fast controller and trimmed at 5 mm (about 35 transitions per
target, so ``heldout_size`` 17,500 is 500 targets), and normalizes the error by a broad reference
set (the held-out set plus as many transitions of i.i.d. random-action motion).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_softae.envs.robots import EnvRecord
from torchrl_softae.envs.robots.soft_arm import (arm_layout, heldout_transitions, random_action_transitions,
                                                 workspace_heldout)
from torchrl_softae.pipeline.entries.entry import EnvEntry
from torchrl_softae.tasks.soft_arm import tip_position

TRANSITIONS_PER_TARGET = 35  # the paper: 17,451 transitions / 500 targets


def _as_td(d: dict, n: int | None = None) -> TensorDict:
    f = lambda x: torch.as_tensor(x[:n], dtype=torch.float32)
    return TensorDict({"observation": f(d["observation"]), "action": f(d["action"]),
                       ("next", "observation"): f(d["next_observation"])}, [len(d["action"][:n])])


def _heldout_v0(points: int):
    def make(n: int, seed: int) -> TensorDict:
        chunks, total, k = [], 0, 0
        while total < n:  # roughly 90 transitions per target
            d = heldout_transitions(max(1, (n - total) // 60), seed + 7919 * k, observed_points=points)
            chunks.append(d)
            total += len(d["action"])
            k += 1
        return _as_td({key: np.concatenate([c[key] for c in chunks]) for key in chunks[0]}, n)

    return make


def _heldout_v1(points: int, period: float):
    def make(n: int, seed: int) -> TensorDict:
        n_targets = max(1, math.ceil(n / TRANSITIONS_PER_TARGET))
        return _as_td(workspace_heldout(n_targets, seed, observed_points=points, control_period=period, progress=True))

    return make


def _reference_v1(points: int, period: float):
    def make(n: int, seed: int) -> TensorDict:
        return _as_td(random_action_transitions(max(1, math.ceil(n / 200)), seed, observed_points=points,
                                                control_period=period), n)

    return make


def entry(record: EnvRecord, tasks: dict) -> EnvEntry:
    from torchrl.envs import GymEnv

    points = record.kwargs["observed_points"]
    period = record.kwargs.get("control_period", 0.02)
    v1 = record.kwargs.get("target_set", "v0") != "v0"
    layout = arm_layout(points)
    groups = {"tip": list(range(3 * points - 3, 3 * points))}
    groups.update({name: list(range(sl.start, sl.stop)) for name, sl in layout.items()})
    return EnvEntry(
        env_id=record.env_id,
        make=lambda: GymEnv(record.env_id),
        tasks=tasks,
        projection=lambda obs: tip_position(obs, points)[..., [0, 2]],
        projection_labels=("tip x [m]", "tip z [m]"),
        heldout=_heldout_v1(points, period) if v1 else _heldout_v0(points),
        reference=_reference_v1(points, period) if v1 else None,
        defaults={"planner": {"horizon": 10}, **({"heldout_size": 17500} if v1 else {})},
        version="3" if v1 else "2",
        accuracy_groups=groups,
        description=f"PyElastica Cosserat-rod arm, {6 * points + 7 * (points - 1)}D state, 12 torques, "
                    f"{period * 1e3:.0f} ms control period",
    )
