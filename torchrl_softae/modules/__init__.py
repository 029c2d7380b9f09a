"""Learned models and planners: the ensemble world model (plain torch, :mod:`.ensemble`), the
engine that runs its inference fast (:mod:`.engine`, attached to every model here) and the
planners."""
from torchrl_softae.modules.ensemble import (
    EnsembleLinear,
    EnsembleWorldModel,
    Normalizer,
    attach_engine,
    ensemble_std,
    symexp,
    symlog,
)
from torchrl_softae.modules.engine import DeterministicRollout, InferenceEngine, SampledRollout
from torchrl_softae.modules.engine.precision import fast_bf16_available, resolve_planning_dtype
from torchrl_softae.modules.planners import ICEMPlanner, MPPIPlanner, SequencePlannerBase, colored_noise

attach_engine(InferenceEngine)

__all__ = [
    "DeterministicRollout",
    "EnsembleLinear",
    "EnsembleWorldModel",
    "InferenceEngine",
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
