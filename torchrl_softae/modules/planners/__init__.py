"""MPC planners (TensorDict in, action out) over TorchRL envs, on one scoring path
(:class:`~torchrl_softae.modules.planners.common.SequencePlannerBase`)."""
from torchrl_softae.modules.planners.colored_noise import colored_noise
from torchrl_softae.modules.planners.common import SequencePlannerBase
from torchrl_softae.modules.planners.contract import ActionSequenceEvaluator, rollout_returns
from torchrl_softae.modules.planners.icem import ICEMPlanner
from torchrl_softae.modules.planners.mppi import MPPIPlanner

__all__ = ["ActionSequenceEvaluator", "ICEMPlanner", "MPPIPlanner", "SequencePlannerBase", "colored_noise",
           "rollout_returns"]
