"""What the pipeline needs to know about one environment (:class:`EnvEntry`); one module per robot
family in :mod:`torchrl_softae.pipeline.entries` builds them, the catalog keeps them."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from torchrl_softae.tasks import Task

__all__ = ["EnvEntry"]


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
        defaults: nested overrides of :class:`~torchrl_softae.pipeline.config.ExploreConfig` (paper values per env).
        reference: ``(n, seed) -> transitions``, as many added to the held-out set to form the
            fixed reference set whose per-dimension std normalizes the model error (default:
            none, the held-out set alone).
        heldout_file: the user's held-out transitions (``--heldout FILE``) replacing ``heldout``.
        replayable: an episode is a function of its seed and its actions (a simulator), so an
            evaluation killed mid-episode resumes by replaying the actions it took. Never set it
            for real hardware: a replay would move the robot. The catalog's envs (simulators and
            the SoPrA twin) are; an outside env is not (its evaluation resumes at a task's start).
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
    version: str | None = "1"  # bump when the physics changes: keys the held-out cache (None: not shared across runs)
    accuracy_groups: dict = field(default_factory=dict)  # extra normalized-MSE reports, name -> dims
    reference: Callable[[int, int], TensorDictBase] | None = None  # extra broad transitions for the metric's scale
    heldout_file: str | None = None
    replayable: bool = False
    _specs: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def specs(self) -> tuple:
        """``(observation_spec, action_spec)`` of the env, read from one instance built (and closed)
        at the first call and kept for the process: loading a run and building its policy learner
        need the specs, not a second connection to the robot (for SoPrA, a valve/mocap session)."""
        if self._specs is None:
            env = self.make()
            try:
                self._specs = (env.observation_spec.clone(), env.action_spec.clone())
            finally:
                env.close()
        return self._specs

    def project(self, data) -> torch.Tensor:
        """``data`` (a tensordict of transitions) -> ``(N, 2)`` coverage coordinates."""
        return self.projection(*(data.get(k) for k in self.projection_keys))
