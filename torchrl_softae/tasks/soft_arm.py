"""Tasks of the soft continuum arm: (i) ``reach-close`` and (ii) ``reach-far`` (Table S5), and on
``SoftArm-v1`` ``reach-any``: a target drawn per episode from the held-out target distribution
(uniform over the reachable workspace volume)."""
from __future__ import annotations

import numpy as np
import torch

from torchrl_softae.envs.robots.soft_arm import TARGET_SETS, arm_layout
from torchrl_softae.tasks.base import Task
from torchrl_softae.envs.robots.reach import reach_reward

__all__ = ["tip_position", "reach_task", "tasks"]


def tip_position(observation: torch.Tensor, points: int) -> torch.Tensor:
    """``(*B, d_s)`` arm observation -> ``(*B, 3)`` tip position (base frame)."""
    return observation[..., arm_layout(points)["positions"]][..., -3:]


def reach_task(name: str, target, points: int, horizon: int = 200) -> Task:
    """Reward g(||p_tip - p_target||) in (0, 1] (see :func:`~torchrl_softae.envs.robots.reach.reach_reward`)."""
    target_t = torch.as_tensor(np.asarray(target), dtype=torch.float32)

    def reward(obs, action, next_obs):
        return reach_reward((tip_position(next_obs, points) - target_t.to(next_obs.device)).norm(dim=-1))

    def metrics(traj):
        err = (tip_position(traj["next", "observation"], points) - target_t.to(traj.device)).norm(dim=-1)
        return {"final_error_mm": float(err[-1]) * 1e3, "min_error_mm": float(err.min()) * 1e3}

    return Task(name, reward, horizon, metrics, f"reach {np.round(np.asarray(target), 3).tolist()}",
                params={"target": np.asarray(target).tolist()}, success_metric="final_error_mm")


def reach_any_task(points: int, control_period: float, horizon: int = 200) -> Task:
    """A target per evaluation episode, drawn like the held-out set's (reachable by construction:
    the simulator's settled tip of a held action spread over the workspace volume)."""

    def instantiate(seed: int) -> Task:
        from torchrl_softae.envs.robots.soft_arm import SoftArmEnv, settle_tip, workspace_goal_actions

        goal = workspace_goal_actions(1, seed)[0]
        target = settle_tip(SoftArmEnv(observed_points=points, control_period=control_period), goal, steps=20)
        return reach_task("reach-any", target, points, horizon)

    return Task("reach-any", lambda s, a, s2: torch.zeros(s2.shape[:-1]), horizon, None,
                "reach a target drawn from the workspace volume (one per episode)", success_metric="final_error_mm",
                instantiate=instantiate)


def tasks(observed_points: int = 5, control_period: float = 0.02, target_set: str = "v0") -> dict[str, Task]:
    out = {name: reach_task(name, tgt, observed_points) for name, tgt in TARGET_SETS[target_set].items()}
    if target_set != "v0":
        out["reach-any"] = reach_any_task(observed_points, control_period)
    return out
