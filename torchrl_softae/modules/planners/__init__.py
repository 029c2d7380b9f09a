"""MPC planners (TensorDict in, action out) over TorchRL envs, on one scoring path
(:class:`~torchrl_softae.modules.planners.common.SequencePlannerBase`)."""
from torchrl_softae.modules.planners.colored_noise import colored_noise
from torchrl_softae.modules.planners.common import SequencePlannerBase
from torchrl_softae.modules.planners.icem import ICEMPlanner
from torchrl_softae.modules.planners.mppi import MPPIPlanner

__all__ = ["ICEMPlanner", "MPPIPlanner", "SequencePlannerBase", "colored_noise"]
