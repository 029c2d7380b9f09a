"""Keep a run alive when the real system misbehaves: faults end the episode, they do not crash it."""
from __future__ import annotations

import warnings

import torch
from tensordict import TensorDictBase
from torchrl.data import Categorical, Composite
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.transforms import Transform

__all__ = ["GuardedEnv", "EnvFaultWarning"]


class EnvFaultWarning(RuntimeWarning):
    """The wrapped env raised or returned a non-finite observation; the episode was ended."""


class _FaultFlag(Transform):
    """Declares the ``env_fault`` flag (False on normal steps)."""

    def __init__(self, key: str):
        super().__init__(in_keys=[], out_keys=[key])
        self.key = key

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        if self.key not in next_tensordict.keys():
            next_tensordict.set(self.key, torch.zeros(*next_tensordict.batch_size, 1, dtype=torch.bool))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        observation_spec[self.key] = Categorical(2, (*observation_spec.shape, 1), dtype=torch.bool)
        return observation_spec


class GuardedEnv(TransformedEnv):
    """Wraps a real env so that an exception or a NaN/inf observation terminates the episode.

    The faulty step is returned as a terminal transition with ``("next", "env_fault") = True`` and
    a warning that names the cause; every transition before it is kept by the collector, which
    then resets the env and carries on. A fault during ``reset`` is not recoverable and raises.
    """

    def __init__(self, env: EnvBase, observation_key: str = "observation", fault_key: str = "env_fault"):
        super().__init__(env, _FaultFlag(fault_key))
        self.observation_key = observation_key
        self.fault_key = fault_key
        self.num_faults = 0

    def _fault_step(self, tensordict: TensorDictBase, reason: str) -> TensorDictBase:
        self.num_faults += 1
        warnings.warn(f"{type(self.base_env).__name__}: {reason}; ending the episode (data so far is kept)",
                      EnvFaultWarning, stacklevel=2)
        out = self.full_observation_spec.zero(tensordict.batch_size)
        obs = out.get(self.observation_key)
        out.set(self.observation_key, torch.full_like(obs, float("nan")))
        out.update(self.full_reward_spec.zero(tensordict.batch_size))
        done = self.full_done_spec.zero(tensordict.batch_size)
        for key in ("done", "terminated"):
            if key in done.keys():
                done.set(key, torch.ones_like(done.get(key)))
        out.update(done)
        out.set(self.fault_key, torch.ones(*tensordict.batch_size, 1, dtype=torch.bool))
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        try:
            out = super()._step(tensordict)
        except Exception as err:  # a real robot/simulator error must not lose the run
            return self._fault_step(tensordict, f"step raised {type(err).__name__}: {err}")
        obs = out.get(self.observation_key)
        if not torch.isfinite(obs).all():
            bad = (~torch.isfinite(obs)).nonzero()[0].tolist()
            fault = self._fault_step(tensordict, f"non-finite {self.observation_key!r} (first at index {bad})")
            fault.set(self.observation_key, obs)  # keep what the env returned, NaN included
            return fault
        return out
