"""The speed wing of the ensemble: inference paths, packed weights, compiled kernels and their
wrappers, CPU probing and planning rollouts. It imports the model
(:mod:`torchrl_softae.modules.ensemble`); the model never imports it: :mod:`torchrl_softae.modules`
attaches an :class:`InferenceEngine` to every model (``model.engine``)."""
from torchrl_softae.modules.engine.network import InferenceEngine
from torchrl_softae.modules.engine.rollouts import DeterministicRollout, SampledRollout

__all__ = ["InferenceEngine", "DeterministicRollout", "SampledRollout"]
