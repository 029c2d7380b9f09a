"""Pipeline entry of the soft arm: tip x-z coverage, held-out reaching rollouts, per-group accuracy."""
from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_softae.envs.robots import EnvRecord
from torchrl_softae.envs.robots.soft_arm import heldout_transitions
from torchrl_softae.pipeline.catalog import EnvEntry
from torchrl_softae.tasks.soft_arm import tip_position


def _heldout(points: int):
    def make(n: int, seed: int) -> TensorDict:
        chunks, total, k = [], 0, 0
        while total < n:  # roughly 90 transitions per target
            d = heldout_transitions(max(1, (n - total) // 60), seed + 7919 * k, observed_points=points)
            chunks.append(d)
            total += len(d["action"])
            k += 1
        cat = {key: np.concatenate([c[key] for c in chunks])[:n] for key in chunks[0]}
        f = lambda x: torch.as_tensor(x, dtype=torch.float32)
        return TensorDict({"observation": f(cat["observation"]), "action": f(cat["action"]),
                           ("next", "observation"): f(cat["next_observation"])}, [n])

    return make


def entry(record: EnvRecord, tasks: dict) -> EnvEntry:
    from torchrl.envs import GymEnv

    points = record.kwargs["observed_points"]
    return EnvEntry(
        env_id=record.env_id,
        make=lambda: GymEnv(record.env_id),
        tasks=tasks,
        projection=lambda obs: tip_position(obs, points)[..., [0, 2]],
        projection_labels=("tip x [m]", "tip z [m]"),
        heldout=_heldout(points),
        defaults={"planner": {"horizon": 10}},
        version="2",
        accuracy_groups={"tip": list(range(3 * points - 3, 3 * points)),
                         "positions": list(range(3 * points))},
        description=f"PyElastica Cosserat-rod arm, {6 * points + 7 * (points - 1)}D state, 12 torques",
    )
