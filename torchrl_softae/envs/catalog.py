"""Every environment the exploration pipeline knows: how to build it, its tasks, its plots."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from torchrl_softae.tasks.base import Task

__all__ = ["EnvEntry", "register_env_entry", "get_env_entry", "env_ids"]


@dataclass
class EnvEntry:
    """What the pipeline needs to explore and evaluate one environment.

    Args:
        env_id: the name used on the command line (``softae explore --env ID``).
        make: ``() -> EnvBase``: a TorchRL env with an ``"observation"`` entry and a bounded action.
        tasks: the downstream tasks, by name.
        projection: ``(N, d) -> (N, 2)`` coverage projection for heatmaps, with axis labels; it
            receives the entries ``projection_keys`` of the transitions (default the observation;
            e.g. the fish's world position, which the env reports through ``info``).
        heldout: ``(n, seed) -> transitions`` held-out set (``observation``, ``action``,
            ``("next", "observation")``) from a data source that does not use explored data.
        defaults: nested overrides of :class:`~torchrl_softae.config.ExploreConfig` (paper values per env).
    """

    env_id: str
    make: Callable[[], EnvBase]
    tasks: dict[str, Task]
    projection: Callable[[torch.Tensor], torch.Tensor]
    projection_labels: tuple[str, str]
    heldout: Callable[[int, int], TensorDictBase]
    defaults: dict = field(default_factory=dict)
    description: str = ""
    projection_keys: tuple = ("observation",)
    version: str = "1"  # bump when the physics changes: keys the held-out cache
    accuracy_groups: dict = field(default_factory=dict)  # extra normalized-MSE reports, name -> dims

    def project(self, data) -> torch.Tensor:
        """``data`` (a tensordict of transitions) -> ``(N, 2)`` coverage coordinates."""
        return self.projection(*(data.get(k) for k in self.projection_keys))


_ENTRIES: dict[str, EnvEntry] = {}
_LAZY: dict[str, str] = {  # env id -> module that registers it (imported on first use)
    "Pendulum-v1": "torchrl_softae.envs.classic",
    "Pendulum-hanging": "torchrl_softae.envs.classic",
    "cartpole-swingup": "torchrl_softae.envs.classic",
    "SoftArm-v0": "torchrl_softae.envs.arm_entry",
    "SoftArm136-v0": "torchrl_softae.envs.arm_entry",
    "SoftFish-v0": "torchrl_softae.envs.mujoco_entries",
    "SoftFishTarget-v0": "torchrl_softae.envs.mujoco_entries",
    "MSKLeg-v0": "torchrl_softae.envs.mujoco_entries",
    "SoPrA-v0": "torchrl_softae.envs.sopra.entry",
}


def register_env_entry(entry: EnvEntry) -> None:
    _ENTRIES[entry.env_id] = entry


def env_ids() -> list[str]:
    return sorted(set(_ENTRIES) | set(_LAZY))


def get_env_entry(env_id: str) -> EnvEntry:
    if env_id not in _ENTRIES and env_id in _LAZY:
        import importlib

        importlib.import_module(_LAZY[env_id])
    if env_id not in _ENTRIES:
        raise ValueError(f"unknown env {env_id!r}; valid envs: {', '.join(env_ids())}")
    return _ENTRIES[env_id]
