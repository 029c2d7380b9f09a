"""What the pipeline knows about each environment, derived from the one list
(:data:`torchrl_softae.envs.robots.ENVS`): how to build it for TorchRL, its tasks, its coverage
projection, its held-out set and its per-env config defaults. An env outside the list (a
gymnasium id, ``module:EnvId-v0``, ``module:callable``) gets an entry with defaults read from the
env itself (:mod:`torchrl_softae.pipeline.entries.external`); tasks may be named by
``module:attr`` for any env (:func:`get_tasks`)."""
from __future__ import annotations

import dataclasses
import importlib

from torchrl_softae.envs.robots import ENVS, EnvRecord, get_record
from torchrl_softae.pipeline.entries.entry import EnvEntry
from torchrl_softae.references import BadReference
from torchrl_softae.tasks import Task, load_tasks, tasks_for

__all__ = ["EnvEntry", "get_env_entry", "env_ids", "get_tasks", "get_task", "run_entry", "parse_coverage_dims",
           "heldout_note", "RANDOM_HELDOUT_NOTE", "ENV_HELDOUT"]

#: said wherever the metric of an outside env is shown: random actions are Random's own distribution
RANDOM_HELDOUT_NOTE = "held-out set: random-action episodes (favours Random)"
#: an evaluation's ``heldout_set`` where the run measured on its catalog env's own held-out set
ENV_HELDOUT = "the env's own"


_ENTRIES: dict[str, EnvEntry] = {}


def env_ids() -> list[str]:
    return sorted(r.env_id for r in ENVS)


def get_env_entry(env_id: str) -> EnvEntry:
    """The pipeline entry of ``env_id``, once per process: for a catalog id, built by
    ``torchrl_softae.pipeline.entries.FAMILY.entry`` from the env's record and tasks; for any other
    reference, by :mod:`~torchrl_softae.pipeline.entries.external` (which builds the env once and
    runs ``check_env_specs``). A ValueError names the value and the accepted forms."""
    if env_id not in _ENTRIES:
        if env_id in env_ids():
            record: EnvRecord = get_record(env_id)
            module = importlib.import_module(f"torchrl_softae.pipeline.entries.{record.family}")
            entry = module.entry(record, tasks_for(env_id))
            entry.defaults.setdefault("episode_length", record.max_episode_steps)
            entry.replayable = True  # every catalog env simulates (SoPrA-v0 is the twin)
        else:
            external = importlib.import_module("torchrl_softae.pipeline.entries.external")
            try:
                entry = external.entry(env_id)
            except BadReference:
                if ":" in env_id:
                    raise
                raise BadReference(f"unknown env {env_id!r}: expected a catalog id ({', '.join(env_ids())}), a "
                                   f"registered gymnasium id (e.g. Reacher-v5), module:EnvId-v0 or module:callable") from None
        _ENTRIES[env_id] = entry
    return _ENTRIES[env_id]


def get_tasks(entry: EnvEntry, name: str) -> dict[str, Task]:
    """The tasks ``name`` stands for on ``entry``'s env: one of its own tasks, or all that a
    ``module:attr`` reference names (:func:`~torchrl_softae.tasks.load_tasks`), by ``Task.name``."""
    if name in entry.tasks:
        return {name: entry.tasks[name]}
    if ":" in name:
        return load_tasks(name)
    own = f"one of {', '.join(sorted(entry.tasks))}, or " if entry.tasks else ""
    raise BadReference(f"unknown task {name!r} for env {entry.env_id!r}: expected {own}module:attr naming your own "
                       "Task (or a dict of them, or a function returning either)")


def get_task(entry: EnvEntry, name: str) -> Task:
    """The one task ``name`` stands for (a reference naming several is an error)."""
    tasks = get_tasks(entry, name)
    if len(tasks) != 1:
        raise BadReference(f"task {name!r} names {len(tasks)} tasks ({', '.join(tasks)}): expected exactly one here")
    return next(iter(tasks.values()))


def parse_coverage_dims(text: str, state_dim: int) -> tuple[int, int]:
    """``"i,j"`` -> ``(i, j)``: two distinct state dimensions in ``[0, state_dim)``."""
    try:
        dims = tuple(int(x) for x in str(text).split(","))
    except ValueError:
        dims = ()
    if len(dims) != 2 or dims[0] == dims[1] or not all(0 <= d < state_dim for d in dims):
        raise BadReference(f"coverage_dims={text!r}: expected two distinct state dimensions I,J in [0, {state_dim})")
    return dims


def heldout_note(config) -> str:
    """Where a run's held-out set comes from, when it is not the catalog env's own set: said beside
    the metric wherever it is shown. ``config``: an ``ExploreConfig`` or its dict."""
    get = config.get if isinstance(config, dict) else lambda k: getattr(config, k, None)
    if get("heldout_file"):
        return f"held-out set: {get('heldout_file')}"
    return "" if get("env") in env_ids() else RANDOM_HELDOUT_NOTE


def run_entry(cfg) -> EnvEntry:
    """The entry a run uses: its env's, with the run's own coverage dimensions (``coverage_dims``)
    and held-out file (``heldout_file``) where its config sets them."""
    entry = get_env_entry(cfg.env)
    changes = {}
    if cfg.coverage_dims:
        i, j = parse_coverage_dims(cfg.coverage_dims, entry.specs()[0]["observation"].shape[-1])
        changes.update(projection=lambda obs: obs[..., [i, j]], projection_keys=("observation",),
                       projection_labels=(f"observation[{i}]", f"observation[{j}]"))
    if cfg.heldout_file:
        changes.update(heldout_file=cfg.heldout_file, reference=None)
    if not changes:
        return entry
    specialized = dataclasses.replace(entry, **changes)
    specialized._specs = entry._specs  # the specs need no second env (a robot's session)
    return specialized
