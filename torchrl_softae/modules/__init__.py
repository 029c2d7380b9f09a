"""Learned models and planners."""
from torchrl_softae.modules.ensemble import (
    DeterministicRollout,
    EnsembleLinear,
    EnsembleWorldModel,
    Normalizer,
    SampledRollout,
    ensemble_std,
    symexp,
    symlog,
)
from torchrl_softae.modules.planners import ICEMPlanner, MPPIPlanner, SequencePlannerBase, colored_noise
from torchrl_softae.modules.precision import fast_bf16_available, resolve_planning_dtype

__all__ = [
    "DeterministicRollout",
    "EnsembleLinear",
    "EnsembleWorldModel",
    "Normalizer",
    "SampledRollout",
    "ensemble_std",
    "symlog",
    "symexp",
    "ICEMPlanner",
    "MPPIPlanner",
    "SequencePlannerBase",
    "colored_noise",
    "fast_bf16_available",
    "resolve_planning_dtype",
]
