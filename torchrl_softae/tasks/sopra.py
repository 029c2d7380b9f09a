"""Tasks of SoPrA: (ix) ``reach-close`` and (x) ``reach-far``, 20 steps (Tables S5, S6)."""
from __future__ import annotations

import numpy as np
import torch

from torchrl_softae.envs.robots.sopra.env import SOPRA_TARGETS
from torchrl_softae.tasks.base import Task
from torchrl_softae.envs.robots.reach import reach_reward

__all__ = ["sopra_reach_task", "tasks"]


def sopra_reach_task(name: str, target, horizon: int = 20) -> Task:
    tgt = torch.as_tensor(np.asarray(target), dtype=torch.float32)

    def reward(obs, action, next_obs):
        return reach_reward((next_obs[..., 0:3] - tgt.to(next_obs.device)).norm(dim=-1))

    def metrics(traj):
        err = (traj["next", "observation"][..., 0:3] - tgt.to(traj.device)).norm(dim=-1) * 1e3
        return {"final_error_mm": float(err[-1]), "min_error_mm": float(err.min())}

    return Task(name, reward, horizon, metrics, f"reach {np.round(np.asarray(target), 4).tolist()}",
                params={"target": np.asarray(target).tolist()}, success_metric="final_error_mm")


def tasks() -> dict[str, Task]:
    return {name: sopra_reach_task(name, t) for name, t in SOPRA_TARGETS.items()}
