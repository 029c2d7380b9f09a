"""Pipeline entry of the fish: world x-y coverage, held-out travelling-wave gaits (random
frequency, phase lag, amplitude and bias; no explored data)."""
from __future__ import annotations

import math

import numpy as np
from tensordict import TensorDict

from torchrl_softae.envs.robots import EnvRecord
from torchrl_softae.pipeline.entries.entry import EnvEntry
from torchrl_softae.pipeline.entries.scripted import gym_env_with_info, scripted_rollouts


def _wave_policy(rng):
    freq, phase, amp = rng.uniform(0.5, 4.0), rng.uniform(-1.2, 1.2), rng.uniform(0.2, 1.0)
    bias = rng.uniform(-0.5, 0.5) * (rng.random() < 0.5)

    def policy(k):
        t = 0.02 * k
        a = [amp * math.sin(2 * math.pi * freq * t - phase * i) + bias for i in range(4)]
        return np.clip(np.array(a, dtype=np.float32), -1, 1)

    return policy


def _heldout(with_target: bool):
    def make(n: int, seed: int) -> TensorDict:
        from torchrl_softae.envs.robots.fish import SoftFishEnv

        return scripted_rollouts(lambda: SoftFishEnv(with_target=with_target), _wave_policy, n, seed, "position", 200)

    return make


def entry(record: EnvRecord, tasks: dict) -> EnvEntry:
    with_target = record.kwargs["with_target"]
    return EnvEntry(
        env_id=record.env_id,
        make=lambda: gym_env_with_info(record.env_id, "position", 2),
        tasks=tasks,
        projection=lambda pos: pos,
        projection_keys=("position",),
        projection_labels=("x [m]", "y [m]"),
        heldout=_heldout(with_target),
        defaults={"train": {"max_grad_steps": 7500}, "planner": {"horizon": 100 if with_target else 10}},
        description=f"MuJoCo articulated fish in fluid, {18 if with_target else 15}D state, 4 joint torques",
    )


__all__ = ["entry"]
