"""Tasks of Pendulum-v1 and Pendulum-hanging; observation = (cos th, sin th, thdot), action = torque."""
from __future__ import annotations

import torch

from torchrl_softae.tasks.base import Task

__all__ = ["pendulum_angle", "tasks"]


def pendulum_angle(obs: torch.Tensor) -> torch.Tensor:
    return torch.atan2(obs[..., 1], obs[..., 0])


def _swingup_reward(obs, action, next_obs):
    # gymnasium's Pendulum reward, written on the observation (it depends on s and a only)
    th, thdot = pendulum_angle(obs), obs[..., 2]
    return -(th.square() + 0.1 * thdot.square() + 0.001 * action[..., 0].square())


def _upright_metrics(traj):
    up = (pendulum_angle(traj["next", "observation"]).abs() < 0.3).float()
    return {"upright_fraction_last_half": float(up[..., up.shape[-1] // 2 :].mean())}


def _spin_reward(obs, action, next_obs):
    return next_obs[..., 2]  # counter-clockwise angular velocity


def tasks() -> dict[str, Task]:
    return {
        "swingup": Task("swingup", _swingup_reward, 200, _upright_metrics, "swing up and balance (gymnasium's reward)",
                        success_metric="upright_fraction_last_half"),
        "spin": Task("spin", _spin_reward, 200, None, "spin counter-clockwise as fast as possible"),
    }
