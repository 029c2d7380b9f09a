"""Pipeline entry of dm_control's cartpole (through TorchRL's DMControlEnv): (pole angle, cart
position) coverage, held-out transitions from uniform states stepped by the true physics."""
from __future__ import annotations

import math

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_softae.envs.robots import EnvRecord
from torchrl_softae.pipeline.entries.entry import EnvEntry

__all__ = ["entry"]


def _make_cartpole():
    from torchrl.envs import CatTensors, Compose, DMControlEnv, DoubleToFloat, TransformedEnv

    return TransformedEnv(
        DMControlEnv("cartpole", "swingup"),
        Compose(CatTensors(["position", "velocity"], "observation", del_keys=True), DoubleToFloat()),
    )


def _cartpole_heldout(n: int, seed: int) -> TensorDict:
    """Uniform states (x, phi, x_dot, phi_dot) and forces, stepped by the true dm_control physics."""
    from dm_control import suite

    env = suite.load("cartpole", "swingup", task_kwargs={"random": seed})
    rng = np.random.default_rng(seed)
    physics = env.physics
    obs, act, nxt = np.zeros((n, 5)), rng.uniform(-1, 1, (n, 1)), np.zeros((n, 5))

    def observe():
        o = env.task.get_observation(physics)
        return np.concatenate([o["position"], o["velocity"]])

    for i in range(n):
        env.reset()
        with physics.reset_context():
            physics.named.data.qpos["slider"] = rng.uniform(-1.5, 1.5)
            physics.named.data.qpos["hinge_1"] = rng.uniform(-math.pi, math.pi)
            physics.named.data.qvel["slider"] = rng.uniform(-3, 3)
            physics.named.data.qvel["hinge_1"] = rng.uniform(-8, 8)
        obs[i] = observe()
        env.step(act[i])
        nxt[i] = observe()
    f = lambda x: torch.as_tensor(x, dtype=torch.float32)
    return TensorDict({"observation": f(obs), "action": f(act), ("next", "observation"): f(nxt)}, [n])


def entry(record: EnvRecord, tasks: dict) -> EnvEntry:
    return EnvEntry(
        env_id=record.env_id,
        make=_make_cartpole,
        tasks=tasks,
        projection=lambda obs: torch.stack([torch.atan2(obs[..., 2], obs[..., 1]), obs[..., 0]], -1),
        projection_labels=("pole angle [rad]", "cart position [m]"),
        heldout=_cartpole_heldout,
        defaults={"planner": {"horizon": 20}},
        description="dm_control cartpole through TorchRL's DMControlEnv (5D state, 1 force)",
    )
