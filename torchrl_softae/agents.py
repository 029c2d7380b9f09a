"""From a trained ensemble to a policy for the real env, per exploration method / task.

    random    uniform actions                                           (baseline)
    mean-ae   iCEM on EnsembleModelEnv("mean")       + UncertaintyReward
    pets-ae   iCEM on EnsembleModelEnv("sample")     + UncertaintyReward (trajectory sampling)
    softae    iCEM on EnsembleModelEnv("optimistic") + HallucinatedControl(beta) + UncertaintyReward
    hucrl     iCEM on EnsembleModelEnv("optimistic") + HallucinatedControl(beta) + TaskReward(task)
    task      iCEM on EnsembleModelEnv(mean by default) + TaskReward(task)      (zero-shot control)
"""
from __future__ import annotations

import time

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded
from torchrl.envs import Compose, EnvBase, TransformedEnv
from torchrl.envs.utils import RandomPolicy

from torchrl_softae.config import ExploreConfig, ModelConfig, PlannerConfig
from torchrl_softae.envs import EnsembleModelEnv, HallucinatedControl, RealActionPolicy, UncertaintyReward
from torchrl_softae.modules import EnsembleWorldModel, ICEMPlanner
from torchrl_softae.tasks.base import Task, TaskReward

__all__ = ["build_world_model", "build_planner_policy", "build_exploration_policy", "PlannerPolicy"]


def build_world_model(cfg: ModelConfig, observation_dim: int, action_dim: int) -> EnsembleWorldModel:
    return EnsembleWorldModel(
        observation_dim, action_dim, ensemble_size=cfg.ensemble_size, num_cells=cfg.num_cells,
        depth=cfg.depth, probabilistic=cfg.probabilistic,
    )


class PlannerPolicy(RealActionPolicy):
    """An MPC planner as a collector policy: plans, then writes only the real action (first d_a
    dims; the rest is hallucinated control). Counts planning calls and time (``calls``,
    ``seconds``) and drives an optional tqdm bar."""

    def __init__(self, planner: ICEMPlanner, action_dim: int, progress=None):
        super().__init__(planner, action_dim)
        self.progress = progress
        self.calls, self.seconds = 0, 0.0

    def forward(self, tensordict):
        t = time.perf_counter()
        tensordict = super().forward(tensordict)
        self.seconds += time.perf_counter() - t
        self.calls += 1
        if self.progress is not None:
            self.progress.update(1)
        return tensordict


def _planner(env: EnvBase, cfg: PlannerConfig, seed: int) -> ICEMPlanner:
    return ICEMPlanner(
        env, planning_horizon=cfg.horizon, optim_steps=cfg.optim_steps, num_candidates=cfg.num_candidates,
        top_k=cfg.top_k, num_particles=cfg.num_particles, noise_beta=cfg.noise_beta,
        elite_fraction=cfg.elite_fraction, precision=cfg.precision, time_budget=cfg.time_budget, seed=seed,
    )


def build_planner_policy(
    model: EnsembleWorldModel,
    action_spec: Bounded,
    planner_cfg: PlannerConfig,
    *,
    mode: str,
    reward: str | Task,
    beta: float = 2.0,
    uncertainty_scale: torch.Tensor | None = None,
    seed: int = 0,
    progress=None,
) -> PlannerPolicy:
    """iCEM over the ensemble with the exploration reward (``reward="uncertainty"``) or a task.

    ``mode="optimistic"`` adds the hallucinated control; the returned policy emits real actions only.
    """
    d_a = model.action_dim
    action_spec = action_spec.clone().to("cpu")
    action_spec = Bounded(action_spec.space.low.float(), action_spec.space.high.float(), action_spec.shape, dtype=torch.float32)
    model_env = EnsembleModelEnv(model, action_spec=action_spec, mode=mode)
    model_env.set_seed(seed)
    transforms = []
    if mode == "optimistic":
        transforms.append(HallucinatedControl(beta))
    if reward == "uncertainty":
        transforms.append(UncertaintyReward(scale=uncertainty_scale))
    else:
        transforms.append(TaskReward(reward, action_dim=d_a))
    env = TransformedEnv(model_env, Compose(*transforms))
    return PlannerPolicy(_planner(env, planner_cfg, seed), d_a, progress)


def build_exploration_policy(
    cfg: ExploreConfig, model: EnsembleWorldModel, real_env: EnvBase, task: Task | None, seed: int, progress=None
) -> TensorDictModuleBase:
    """The data-collection policy of episode n for ``cfg.method``."""
    if cfg.method == "random":
        return RandomPolicy(real_env.action_spec)
    scale = None
    if cfg.normalize_uncertainty and bool(model.input_normalizer.fitted):
        # sigma per dimension relative to the data's state std, so units do not decide the norm
        scale = model.input_normalizer.scale[: model.observation_dim].clone()
    mode, reward = {
        "mean-ae": ("mean", "uncertainty"),
        "pets-ae": ("sample", "uncertainty"),
        "softae": ("optimistic", "uncertainty"),
        "hucrl": ("optimistic", task),
    }[cfg.method]
    return build_planner_policy(
        model, real_env.action_spec, cfg.planner, mode=mode, reward=reward, beta=cfg.beta,
        uncertainty_scale=scale, seed=seed, progress=progress,
    )
