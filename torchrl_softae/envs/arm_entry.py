"""Pipeline entries of the soft arm: tasks (i)/(ii), tip x-z coverage, held-out reaching rollouts."""
from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_softae.envs.catalog import EnvEntry, register_env_entry
from torchrl_softae.envs.soft_arm import ARM_TARGETS, arm_layout, heldout_transitions, reach_reward
from torchrl_softae.tasks.base import Task


def _tip(obs: torch.Tensor, points: int) -> torch.Tensor:
    pos = obs[..., arm_layout(points)["positions"]]
    return pos[..., -3:]


def reach_task(name: str, target, points: int, horizon: int = 200) -> Task:
    """Reward g(||p_tip - p_target||) in (0, 1] (Table S6, footnote; see ``reach_reward``)."""
    target_t = torch.as_tensor(np.asarray(target), dtype=torch.float32)

    def reward(obs, action, next_obs):
        return reach_reward((_tip(next_obs, points) - target_t).norm(dim=-1))

    def metrics(traj):
        tip = _tip(traj["next", "observation"], points)
        err = (tip - target_t).norm(dim=-1)
        return {"final_error_mm": float(err[-1]) * 1e3, "min_error_mm": float(err.min()) * 1e3}

    return Task(name, reward, horizon, metrics, f"reach {np.round(np.asarray(target), 3).tolist()}",
                params={"target": np.asarray(target).tolist()})


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


def _entry(env_id: str, points: int) -> EnvEntry:
    from torchrl.envs import GymEnv

    return EnvEntry(
        env_id=env_id,
        make=lambda: GymEnv(env_id),
        tasks={name: reach_task(name, tgt, points) for name, tgt in ARM_TARGETS.items()},
        projection=lambda obs: _tip(obs, points)[..., [0, 2]],
        projection_labels=("tip x [m]", "tip z [m]"),
        heldout=_heldout(points),
        defaults={"episode_length": 200, "planner": {"horizon": 10}},
        version="2",
        accuracy_groups={"tip": list(range(3 * points - 3, 3 * points)),
                         "positions": list(range(3 * points))},
        description=f"PyElastica Cosserat-rod arm, {6 * points + 7 * (points - 1)}D state, 12 torques",
    )


register_env_entry(_entry("SoftArm-v0", 5))
register_env_entry(_entry("SoftArm136-v0", 11))
