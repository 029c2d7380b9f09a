"""MPC planners (TensorDict in, action out) over TorchRL envs."""
from torchrl_softae.modules.planners.colored_noise import colored_noise
from torchrl_softae.modules.planners.icem import ICEMPlanner

__all__ = ["ICEMPlanner", "colored_noise"]
