"""Tasks as data: a reward of (s, a, s') that plugs into the real env and the model env alike."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from torchrl_softae.modules.planners.contract import PlanningTransform

__all__ = ["Task", "TaskReward", "metric_label"]

_UNITS = ("mm", "m", "rad", "s")  # a metric's name ends with its unit: final_error_mm


def metric_label(metric: str) -> str:
    """A metric's name for tables and axes: ``final_error_mm`` -> ``final error [mm]``."""
    *words, last = metric.split("_")
    return " ".join(words) + f" [{last}]" if words and last in _UNITS else metric.replace("_", " ")


RewardFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class Task:
    """A downstream task [r_t in Table S5].

    Args:
        name: short id used on the command line (``softae evaluate --task NAME``).
        reward_fn: ``(s, a, s') -> r`` on tensors ``(*B, d_s)``, ``(*B, d_a)``, ``(*B, d_s)``,
            returning ``(*B,)`` or ``(*B, 1)``; vectorized, so planners score whole populations.
        horizon: episode length used for evaluation.
        metrics_fn: optional ``trajectory tensordict -> {name: float}`` success metrics
            (e.g. final tip error in mm), computed on real rollouts.
        description: one line for ``--help`` and reports.
        params: task parameters worth recording (e.g. the target).
        success_metric: the key of ``metrics_fn``'s output that says whether the task was solved
            (shown next to the return in reports), if any.
        instantiate: for a family of tasks (e.g. "reach any target"), ``seed -> Task``: the
            concrete task of one evaluation episode.
        advance: for a time-varying task (tracking a reference path), ``t -> None``: moves the
            reference to step ``t``'s; the evaluation calls it before each action, so the planner and
            the reward see the reference of the step being planned.
    """

    name: str
    reward_fn: RewardFn
    horizon: int
    metrics_fn: Callable[[TensorDictBase], dict] | None = None
    description: str = ""
    params: dict = field(default_factory=dict)
    success_metric: str | None = None
    instantiate: Callable[[int], "Task"] | None = None
    advance: Callable[[int], None] | None = None

    def reward(self, observation: torch.Tensor, action: torch.Tensor, next_observation: torch.Tensor) -> torch.Tensor:
        r = self.reward_fn(observation, action, next_observation)
        if r.shape == observation.shape[:-1]:
            r = r.unsqueeze(-1)
        return r

    def for_episode(self, seed: int) -> "Task":
        """The concrete task of the evaluation episode with ``seed`` (itself unless a family)."""
        return self if self.instantiate is None else self.instantiate(seed)

    def metrics(self, trajectory: TensorDictBase) -> dict:
        return {} if self.metrics_fn is None else dict(self.metrics_fn(trajectory))


class TaskReward(Transform, PlanningTransform):
    """Replaces the env's reward with ``task.reward(s, a, s')``.

    Works on the real env (the task reward then also is what is reported) and on an
    :class:`~torchrl_softae.envs.EnsembleModelEnv` for zero-shot planning. Behind a
    :class:`~torchrl_softae.envs.transforms.HallucinatedControl` (H-UCRL), pass ``action_dim`` so the
    task sees only the real action ``a``, not the hallucinated ``eta``.
    """

    def __init__(self, task: Task, action_dim: int | None = None, observation_key="observation", action_key="action"):
        super().__init__(in_keys=[observation_key], out_keys=["reward"])
        self.task = task
        self.action_dim = action_dim
        self.observation_key = observation_key
        self.action_key = action_key

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(self.observation_key)
        act = tensordict.get(self.action_key)
        if self.action_dim is not None:
            act = act[..., : self.action_dim]
        nxt = next_tensordict.get(self.observation_key)
        r = self.task.reward(obs, act, nxt).to(nxt.dtype)
        next_tensordict.set("reward", r)
        return next_tensordict

    def plan_reward(self, observation, action, next_observation, epistemic_std, reward):
        if self.action_dim is not None:
            action = action[..., : self.action_dim]
        return self.task.reward(observation, action, next_observation).to(next_observation.dtype)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return tensordict_reset

    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        reward_spec["reward"] = Unbounded((*reward_spec.shape, 1), device=reward_spec.device)
        return reward_spec

    def __repr__(self) -> str:
        return f"{type(self).__name__}(task={self.task.name!r})"
