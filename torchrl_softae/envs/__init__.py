"""Environments: the learned-model env and its transforms (TorchRL pieces), a fault guard for real
envs, and under :mod:`torchrl_softae.envs.robots` the robots and the list of env ids.

Names load on first access, so that importing a robot (``torchrl_softae.envs.robots...``) or
registering the gymnasium ids does not import TorchRL.
"""
import importlib

_EXPORTS = {
    "EnsembleModelEnv": "torchrl_softae.envs.model_env",
    "PROPAGATION_MODES": "torchrl_softae.envs.model_env",
    "ActionSequenceEvaluator": "torchrl_softae.modules.planners.contract",
    "HallucinatedControl": "torchrl_softae.envs.transforms",
    "RealActionPolicy": "torchrl_softae.envs.transforms",
    "UncertaintyReward": "torchrl_softae.envs.transforms",
    "GuardedEnv": "torchrl_softae.envs.guard",
    "EnvFaultWarning": "torchrl_softae.envs.guard",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'torchrl_softae.envs' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
