"""Tasks of SoPrA: (ix) ``reach-close`` and (x) ``reach-far``, 20 steps (Tables S5, S6);
``reach-any``, a target per episode from the twin's reachable workspace (Fig. 4D's 20 random
targets: the i-th evaluation episode's target is the same for every method); and tracking a square
and a lemniscate in the horizontal plane through the rest tip (Fig. 4E).

The paper does not give the tracking references' size or timing; ours: a 30 mm square and a
40 x 20 mm lemniscate, 80 reference points one control period apart, the MPC's target moved to the
next point at every step, error = horizontal tip distance to that point.
"""
from __future__ import annotations

import numpy as np
import torch

from torchrl_softae.envs.robots.reach import reach_reward
from torchrl_softae.envs.robots.sopra.env import SOPRA_TARGETS
from torchrl_softae.tasks.base import Task

__all__ = ["sopra_reach_task", "reach_any_task", "reference_path", "tracking_task", "tasks", "TRACKING_SHAPES"]

TRACKING_SHAPES = ("square", "lemniscate")


def sopra_reach_task(name: str, target, horizon: int = 20) -> Task:
    tgt = torch.as_tensor(np.asarray(target), dtype=torch.float32)

    def reward(obs, action, next_obs):
        return reach_reward((next_obs[..., 0:3] - tgt.to(next_obs.device)).norm(dim=-1))

    def metrics(traj):
        err = (traj["next", "observation"][..., 0:3] - tgt.to(traj.device)).norm(dim=-1) * 1e3
        return {"final_error_mm": float(err[-1]), "min_error_mm": float(err.min())}

    return Task(name, reward, horizon, metrics, f"reach {np.round(np.asarray(target), 4).tolist()}",
                params={"target": np.asarray(target).tolist()}, success_metric="final_error_mm")


def _twin(seed: int):
    from torchrl_softae.envs.robots.sopra.env import SoPrAEnv

    env = SoPrAEnv("sim", seed=seed, install_signal_handlers=False)
    env.set_seed(seed)  # as the evaluation seeds its env: the same twin noise, the same rest tip
    return env


def reach_any_task(horizon: int = 20) -> Task:
    """A target per evaluation episode: the twin's settled tip under random pressures within the
    safety cap (:meth:`SoPrAEnv.sample_target`), drawn from the episode's seed."""

    def instantiate(seed: int) -> Task:
        env = _twin(seed)
        try:
            target = env.sample_target()
        finally:
            env.close()
        return sopra_reach_task("reach-any", target, horizon)

    return Task("reach-any", lambda s, a, s2: torch.zeros(s2.shape[:-1], device=s2.device), horizon, None,
                "reach a target drawn from the reachable workspace (one per episode)",
                success_metric="final_error_mm", instantiate=instantiate)


def reference_path(shape: str, center, points: int = 80) -> np.ndarray:
    """``(points, 3)`` reference tip positions [m] around ``center``, in its horizontal plane: a
    30 mm square starting at a corner (four edges of equal duration) or a 40 x 20 mm lemniscate."""
    t = np.linspace(0, 1, points)
    if shape == "square":
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * 0.015
        edge = np.minimum((t * 4).astype(int), 3)
        xy = corners[edge] + (corners[edge + 1] - corners[edge]) * (t * 4 - edge)[:, None]
    elif shape == "lemniscate":
        xy = np.stack([0.02 * np.sin(2 * np.pi * t), 0.01 * np.sin(4 * np.pi * t)], 1)
    else:
        raise ValueError(f"reference_path: shape {shape!r}; valid: {', '.join(TRACKING_SHAPES)}")
    center = np.asarray(center, dtype=np.float64)
    return np.hstack([xy + center[:2], np.full((points, 1), center[2])])


def tracking_task(shape: str, points: int = 80) -> Task:
    """Track ``reference_path(shape)`` through the episode's rest tip: at step ``t`` the reward is
    g(||p_tip - r_{t+1}||) (the point the action should reach); the metric is the mean and max
    horizontal distance to it [mm]. ``points - 1`` steps."""

    def instantiate(seed: int) -> Task:
        env = _twin(seed)
        try:
            rest = env.reset()["observation"][:3].double().numpy()
        finally:
            env.close()
        path = torch.as_tensor(reference_path(shape, rest, points), dtype=torch.float32)
        target = path[1].clone()

        def advance(t: int) -> None:
            target.copy_(path[min(t + 1, points - 1)])

        def reward(obs, action, next_obs):
            return reach_reward((next_obs[..., 0:3] - target.to(next_obs.device)).norm(dim=-1))

        def metrics(traj):
            tips = traj["next", "observation"][..., 0:3].cpu()
            err = (tips[:, :2] - path[1: len(tips) + 1, :2]).norm(dim=-1) * 1e3
            return {"mean_error_mm": float(err.mean()), "max_error_mm": float(err.max()),
                    "tips": tips.tolist()}

        return Task(f"track-{shape}", reward, points - 1, metrics, f"track a {shape} through the rest tip",
                    params={"center": rest.tolist()}, success_metric="mean_error_mm", advance=advance)

    return Task(f"track-{shape}", lambda s, a, s2: torch.zeros(s2.shape[:-1], device=s2.device), points - 1, None,
                f"track a {shape} in the horizontal plane through the rest tip", success_metric="mean_error_mm",
                instantiate=instantiate)


def tasks() -> dict[str, Task]:
    out = {name: sopra_reach_task(name, t) for name, t in SOPRA_TARGETS.items()}
    out["reach-any"] = reach_any_task()
    out.update({f"track-{shape}": tracking_task(shape) for shape in TRACKING_SHAPES})
    return out
