"""Downstream tasks as data: a reward of (s, a, s') for the real env and the model env alike.

Each robot family's tasks are in ``torchrl_softae.tasks.FAMILY`` (``soft_arm``, ``fish``, ``leg``,
``sopra``, ``pendulum``, ``cartpole``); :func:`tasks_for` gives those of an env id, and
:func:`load_tasks` those a ``"module:attr"`` reference names (your own tasks, for any env).
"""
from __future__ import annotations

import importlib

from torchrl_softae.tasks.base import Task, TaskReward

__all__ = ["Task", "TaskReward", "tasks_for", "load_tasks"]


def tasks_for(env_id: str) -> dict[str, Task]:
    """The tasks of a registered env id (``torchrl_softae.envs.robots.ENVS``), by name."""
    from torchrl_softae.envs.robots import get_record

    record = get_record(env_id)
    return importlib.import_module(f"torchrl_softae.tasks.{record.family}").tasks(**record.kwargs)


def load_tasks(text: str) -> dict[str, Task]:
    """The tasks ``"module:attr"`` names, by their ``Task.name``: ``attr`` is a :class:`Task`, a dict
    of them, or a zero-argument callable returning either. A
    :class:`~torchrl_softae.references.BadReference` says what was found instead."""
    from torchrl_softae.references import BadReference, import_reference_module, split_reference

    parts = split_reference(text)
    if parts is None:
        raise BadReference(f"task {text!r}: expected module:attr")
    module_name, attr = parts
    module = import_reference_module(module_name, text)
    if not hasattr(module, attr):
        raise BadReference(f"task {text!r}: module {module_name!r} has no attribute {attr!r}")
    obj = getattr(module, attr)
    if callable(obj) and not isinstance(obj, Task):
        try:
            obj = obj()
        except Exception as e:  # the user's function failed: one line naming it
            raise BadReference(f"task {text!r}: calling it raised {type(e).__name__}: {e}") from None
    found = [obj] if isinstance(obj, Task) else list(obj.values()) if isinstance(obj, dict) else None
    if not found or not all(isinstance(t, Task) for t in found):
        raise BadReference(f"task {text!r} is a {type(obj).__name__}: expected a torchrl_softae Task, a dict of "
                           "Tasks, or a function returning either")
    return {t.name: t for t in found}
