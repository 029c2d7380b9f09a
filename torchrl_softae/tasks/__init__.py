"""Downstream tasks as data: a reward of (s, a, s') for the real env and the model env alike.

Each robot family's tasks are in ``torchrl_softae.tasks.FAMILY`` (``soft_arm``, ``fish``, ``leg``,
``sopra``, ``pendulum``, ``cartpole``); :func:`tasks_for` gives those of an env id.
"""
from __future__ import annotations

import importlib

from torchrl_softae.tasks.base import Task, TaskReward

__all__ = ["Task", "TaskReward", "tasks_for"]


def tasks_for(env_id: str) -> dict[str, Task]:
    """The tasks of a registered env id (``torchrl_softae.envs.robots.ENVS``), by name."""
    from torchrl_softae.envs.robots import get_record

    record = get_record(env_id)
    return importlib.import_module(f"torchrl_softae.tasks.{record.family}").tasks(**record.kwargs)
