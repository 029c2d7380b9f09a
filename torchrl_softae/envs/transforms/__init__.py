"""TorchRL transforms: one transform, one job."""
from torchrl_softae.envs.transforms.hallucinated_control import DEFAULT_BETA, HallucinatedControl, RealActionPolicy
from torchrl_softae.envs.transforms.uncertainty_reward import UncertaintyReward

__all__ = ["DEFAULT_BETA", "HallucinatedControl", "RealActionPolicy", "UncertaintyReward"]
