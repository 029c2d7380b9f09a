"""Pipeline entry of Pendulum-v1 and Pendulum-hanging: (angle, angular velocity) coverage,
held-out transitions uniform over the state-action box."""
from __future__ import annotations

import math

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_softae.envs.robots import EnvRecord
from torchrl_softae.pipeline.entries.entry import EnvEntry
from torchrl_softae.tasks.pendulum import pendulum_angle

__all__ = ["entry"]


def _heldout(n: int, seed: int) -> TensorDict:
    """Uniform over the state-action box: th in [-pi, pi), thdot in [-8, 8], u in [-2, 2]."""
    import gymnasium as gym

    env = gym.make("Pendulum-v1").unwrapped
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    th = rng.uniform(-math.pi, math.pi, n)
    thdot = rng.uniform(-8, 8, n)
    u = rng.uniform(-2, 2, n)
    obs, nxt = np.zeros((n, 3)), np.zeros((n, 3))
    for i in range(n):
        env.state = np.array([th[i], thdot[i]])
        obs[i] = [math.cos(th[i]), math.sin(th[i]), thdot[i]]
        nxt[i] = env.step(np.array([u[i]], dtype=np.float32))[0]
    f = lambda x: torch.as_tensor(x, dtype=torch.float32)
    return TensorDict({"observation": f(obs), "action": f(u[:, None]), ("next", "observation"): f(nxt)}, [n])


def entry(record: EnvRecord, tasks: dict) -> EnvEntry:
    from torchrl.envs import GymEnv

    hanging = record.env_id == "Pendulum-hanging"
    return EnvEntry(
        env_id=record.env_id,
        make=lambda: GymEnv(record.env_id),
        tasks=tasks,
        projection=lambda obs: torch.stack([pendulum_angle(obs), obs[..., 2]], -1),
        projection_labels=("angle [rad]", "angular velocity [rad/s]"),
        heldout=_heldout,
        defaults={"planner": {"horizon": 20}},
        description=("Pendulum-v1 starting hanging down at rest (exploration must pump energy)" if hanging
                     else "gymnasium Pendulum-v1 (3D state, 1 torque)"),
    )
