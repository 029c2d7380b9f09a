"""Pipeline entry of the musculoskeletal leg: yaw / foot-height coverage, held-out random periodic
muscle patterns with a random roll (no explored data)."""
from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_softae.envs.robots import EnvRecord
from torchrl_softae.pipeline.entries.entry import EnvEntry
from torchrl_softae.pipeline.entries.scripted import gym_env_with_info, scripted_rollouts

__all__ = ["entry"]


def _muscle_pattern_policy(rng):
    freq, duty, roll = rng.uniform(2.0, 7.0), rng.uniform(0.2, 0.6), rng.uniform(-1, 1)
    levels = rng.uniform(-1, 1, 4)

    def policy(k):
        stance = (0.01 * k * freq) % 1.0 < duty
        hip = levels[:2] if stance else levels[:2][::-1]
        knee = np.array([-1.0, 1.0]) if stance else np.array([1.0, -1.0])
        return np.clip(np.r_[roll, hip, knee * abs(levels[2])], -1, 1).astype(np.float32)

    return policy


def _heldout(n: int, seed: int) -> TensorDict:
    from torchrl_softae.envs.robots.msk_leg import MSKLegEnv

    return scripted_rollouts(MSKLegEnv, _muscle_pattern_policy, n, seed, "foot_height", 500)


def entry(record: EnvRecord, tasks: dict) -> EnvEntry:
    return EnvEntry(
        env_id=record.env_id,
        make=lambda: gym_env_with_info(record.env_id, "foot_height", 1),
        tasks=tasks,
        projection=lambda obs, foot: torch.stack([obs[..., 0], foot[..., 0]], -1),
        projection_keys=("observation", "foot_height"),
        projection_labels=("boom yaw [rad]", "foot height [m]"),
        heldout=_heldout,
        defaults={"planner": {"horizon": 100}},
        description="MuJoCo hopping leg on a boom, HASEL muscles + DC motor, 10D state, 5 actions",
    )
