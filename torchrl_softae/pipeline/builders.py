"""From a trained ensemble to a policy for the real env, per exploration method (the records of
:mod:`torchrl_softae.pipeline.methods`) or task:

    iCEM on EnsembleModelEnv(method.propagation)
         + HallucinatedControl(beta)          where the propagation is optimistic
         + UncertaintyReward | TaskReward     as the method's reward says
    random methods: uniform actions; zero-shot control: a task reward, mean propagation by default.
"""
from __future__ import annotations

import time

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded
from torchrl.envs import Compose, EnvBase, TransformedEnv
from torchrl.envs.utils import RandomPolicy

from torchrl_softae.envs import EnsembleModelEnv, HallucinatedControl, RealActionPolicy, UncertaintyReward
from torchrl_softae.modules import EnsembleWorldModel, ICEMPlanner
from torchrl_softae.pipeline.config import ExploreConfig, ModelConfig, PlannerConfig
from torchrl_softae.pipeline.methods import get_method
from torchrl_softae.tasks.base import Task, TaskReward

__all__ = ["build_world_model", "build_planner_policy", "build_exploration_policy", "PlannerPolicy"]


def build_world_model(cfg: ModelConfig, observation_dim: int, action_dim: int, device=None) -> EnsembleWorldModel:
    return EnsembleWorldModel(
        observation_dim, action_dim, ensemble_size=cfg.ensemble_size, num_cells=cfg.num_cells,
        depth=cfg.depth, probabilistic=cfg.probabilistic, symlog_observations=cfg.symlog, device=device,
        kernels=cfg.kernels,
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
            self.progress.update(max(1, tensordict.numel()))  # a batch of states is that many env steps
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
    beta: float,
    uncertainty_scale: torch.Tensor | None = None,
    seed: int = 0,
    progress=None,
) -> PlannerPolicy:
    """iCEM over the ensemble with the exploration reward (``reward="uncertainty"``) or a task.

    ``mode="optimistic"`` adds the hallucinated control of width ``beta`` (the run's, always: there
    is no default, so evaluation cannot silently plan with another beta than exploration); the
    returned policy emits real actions only. The model env lives on the model's device.
    """
    d_a = model.action_dim
    device = model.input_normalizer.loc.device
    action_spec = Bounded(action_spec.space.low.float().to(device), action_spec.space.high.float().to(device),
                          action_spec.shape, dtype=torch.float32, device=device)
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
    cfg: ExploreConfig, model: EnsembleWorldModel, real_env: EnvBase, task: Task | None, seed: int, progress=None,
    learner=None,
) -> TensorDictModuleBase:
    """The data-collection policy of episode n for ``cfg.method`` (its record says how it acts):
    random actions, iCEM on the model, or (``trains_policy``) the SAC policy of ``learner``, a
    :class:`~torchrl_softae.pipeline.policy.PolicyLearner`, sampling as SAC explores."""
    method = get_method(cfg.method)
    if method.propagation is None:
        return RandomPolicy(real_env.action_spec)
    if method.trains_policy:
        if learner is None:
            raise ValueError(f"method {method.name!r} collects with its SAC policy: pass its learner")
        return learner.policy(deterministic=False)
    scale = None
    if method.reward == "uncertainty" and cfg.normalize_uncertainty and bool(model.input_normalizer.fitted):
        # sigma per dimension relative to the data's state std, so units do not decide the norm
        scale = model.input_normalizer.scale[: model.observation_dim].clone()
    reward = "uncertainty" if method.reward == "uncertainty" else task
    return build_planner_policy(
        model, real_env.action_spec, cfg.planner, mode=method.propagation, reward=reward, beta=cfg.beta,
        uncertainty_scale=scale, seed=seed, progress=progress,
    )
