"""Environments: the learned-model env, transforms, and (registered with gymnasium) robots."""
from torchrl_softae.envs.model_env import PROPAGATION_MODES, EnsembleModelEnv
from torchrl_softae.envs.transforms import HallucinatedControl, RealActionPolicy, UncertaintyReward

__all__ = ["EnsembleModelEnv", "PROPAGATION_MODES", "HallucinatedControl", "RealActionPolicy", "UncertaintyReward"]
