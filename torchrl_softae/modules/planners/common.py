"""What every sequence-sampling MPC planner here shares: the action box, how candidates are scored,
input validation and the planner's own generator, all on the env's device.

Scoring goes through one path (:meth:`SequencePlannerBase.evaluate`): the env's
:meth:`~torchrl_softae.modules.planners.contract.ActionSequenceEvaluator.evaluate_action_sequences` when the
(base) env offers the contract, TorchRL's generic ``env.rollout`` otherwise. Subclasses write
``planning()``, like TorchRL's ``MPCPlannerBase`` subclasses.
"""
from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.modules.planners.common import MPCPlannerBase

from torchrl_softae.modules.planners.contract import PLANNING_PRECISIONS, ActionSequenceEvaluator, rollout_returns

__all__ = ["SequencePlannerBase", "check_positive_int"]


def check_positive_int(owner: str, name: str, value, low: int = 1) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value < low:
        raise ValueError(f"{owner}: {name}={value!r}, expected an int >= {low}")


class SequencePlannerBase(MPCPlannerBase):
    """Base of planners that score sampled action sequences ``(B, N, H, d)`` in ``env``.

    Args:
        env (EnvBase): a batch-unlocked env to plan in (a model env, possibly behind transforms).
        planning_horizon (int): H.
        num_particles (int): rollouts per candidate whose returns are averaged; an
            :class:`~torchrl_softae.modules.planners.contract.ActionSequenceEvaluator` env may need fewer
            (one when its propagation is deterministic) unless ``deduplicate_particles=False``.
        precision (str): ``"fp32"``, ``"bf16"`` or ``"auto"``, passed to the env's evaluator.
        deduplicate_particles (bool): let the env evaluate one particle when they would be identical.
        observation_keys (list, optional): the input entries that make the initial state; default
            the evaluator's ``state_keys``, or every observation entry of a generic env.
        seed (int): seed of the planner's own generator (on the env's device).
    """

    def __init__(
        self,
        env: EnvBase,
        planning_horizon: int,
        num_particles: int = 1,
        precision: str = "fp32",
        deduplicate_particles: bool = True,
        action_key: NestedKey = "action",
        reward_key: NestedKey = ("next", "reward"),
        observation_keys: list | None = None,
        seed: int = 0,
    ):
        owner = type(self).__name__
        check_positive_int(owner, "planning_horizon", planning_horizon)
        check_positive_int(owner, "num_particles", num_particles)
        if precision not in PLANNING_PRECISIONS:
            raise ValueError(f"{owner}: precision={precision!r}, expected one of {', '.join(PLANNING_PRECISIONS)}")
        super().__init__(env=env, action_key=action_key)
        base = env.base_env if isinstance(env, TransformedEnv) else env
        self.evaluator: ActionSequenceEvaluator | None = base if isinstance(base, ActionSequenceEvaluator) else None
        if observation_keys is None:
            observation_keys = (self.evaluator.state_keys if self.evaluator is not None
                                else list(env.full_observation_spec.keys(True, True)))
        self.observation_keys = list(observation_keys)
        self.in_keys = list(self.observation_keys)
        self.planning_horizon = planning_horizon
        self.num_particles = num_particles
        self.precision = precision
        self.deduplicate_particles = deduplicate_particles
        self.reward_key = reward_key
        self.env_device = env.device if env.device is not None else torch.device("cpu")
        self._generator = torch.Generator(device=self.env_device).manual_seed(seed)
        spec = self.action_spec
        d = spec.shape[-1]
        if isinstance(spec, Bounded):
            low = spec.space.low.detach().to(self.env_device, torch.float32).expand(d).clone()
            high = spec.space.high.detach().to(self.env_device, torch.float32).expand(d).clone()
        else:  # unbounded: a unit-scale search around zero, no clipping
            low = torch.full((d,), -math.inf, device=self.env_device)
            high = torch.full((d,), math.inf, device=self.env_device)
        self.register_buffer("_low", low)
        self.register_buffer("_high", high)

    # ------------------------------------------------------------------ state
    #: the attributes one call hands to the next (the warm start); :meth:`reset` clears them
    _warm_start: tuple[str, ...] = ()

    def set_seed(self, seed: int) -> int:
        self._generator.manual_seed(seed)
        return seed

    def reset(self) -> None:
        """Forget the warm start (call at every episode start)."""
        for name in self._warm_start:
            setattr(self, name, None)

    def search_state(self) -> dict:
        """What the next call depends on besides its input: the warm start and the states of the
        random generators it draws from (the planner's, and its model env's, see
        :meth:`~torchrl_softae.modules.planners.contract.ActionSequenceEvaluator.generator_state`).
        A planner given this state by :meth:`load_search_state` takes the actions this one would
        take, so an episode stopped between two calls can go on elsewhere (a killed evaluation)."""
        return {
            "generator": self._generator.get_state(),
            "evaluator_generator": None if self.evaluator is None else self.evaluator.generator_state(),
            "warm_start": {name: getattr(self, name) for name in self._warm_start},
        }

    def load_search_state(self, state: dict) -> None:
        """Continue from :meth:`search_state` (tensors are moved to the env's device)."""
        self._generator.set_state(state["generator"])
        if self.evaluator is not None and state["evaluator_generator"] is not None:
            self.evaluator.set_generator_state(state["evaluator_generator"])
        for name in self._warm_start:
            value = state["warm_start"][name]
            setattr(self, name, None if value is None else value.to(self.env_device))

    @property
    def effective_particles(self) -> int:
        """Rollouts per candidate actually evaluated."""
        if self.evaluator is not None and self.deduplicate_particles:
            return self.evaluator.particles_needed(self.num_particles)
        return self.num_particles

    def centre_and_halfrange(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Centre and half-width of the action box (0 and 1 where a bound is infinite)."""
        finite = torch.isfinite(self._low) & torch.isfinite(self._high)
        mid = torch.where(finite, (self._low + self._high) / 2, torch.zeros_like(self._low))
        half = torch.where(finite, (self._high - self._low) / 2, torch.ones_like(self._low))
        return mid, half

    def sample_candidates(self, mean: torch.Tensor, std: torch.Tensor, noise: torch.Tensor,
                          extra: tuple[torch.Tensor, ...] = ()) -> torch.Tensor:
        """``clip(mean + std * noise)`` followed by the ``extra`` sequences, clipped too: ``(B, n +
        k, H, d)`` for ``noise`` ``(B, n, H, d)`` and ``extra`` ``(B, k_i, H, d)`` each (``mean`` and
        ``std`` broadcast against ``noise``), clipped to the action box. Written into one buffer and
        clipped in place: the same values as adding, concatenating and clipping apart, with two
        passes and three allocations less (each costs a few tens of microseconds right after a
        planner's scoring, ``benchmarks/studies/cold_ops.py``)."""
        B, n = noise.shape[:2]
        out = torch.empty(B, n + sum(e.shape[1] for e in extra), *noise.shape[2:], dtype=noise.dtype,
                          device=noise.device)
        # (not addcmul: on strided noise its loop may fuse the multiply-add, so other bits)
        torch.mul(std, noise, out=out[:, :n]).add_(mean)
        for e in extra:
            out[:, n:n + e.shape[1]] = e
            n += e.shape[1]
        return out.clamp_(self._low, self._high)

    # ------------------------------------------------------------------ scoring
    @torch.no_grad()
    def evaluate(self, observation_td: TensorDictBase, actions: torch.Tensor) -> torch.Tensor:
        """Predicted returns ``(B, N)`` of candidate sequences ``(B, N, H, d)`` from ``(B,)``
        initial states, averaged over particles; non-finite returns are ``-inf``."""
        if self.evaluator is not None:
            return self.evaluator.evaluate_action_sequences(
                observation_td, actions, num_particles=self.effective_particles, env=self.env,
                precision=self.precision, generator=self._generator)
        return rollout_returns(self.env, observation_td, actions, self.num_particles,
                               reward_key=self.reward_key, action_key=self.action_key)

    def validate_input(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The initial states ``(B,)`` of ``tensordict``, or an error naming a missing, misshaped
        or non-finite entry."""
        owner = type(self).__name__
        for key in self.observation_keys:
            x = tensordict.get(key, None)
            if x is None:
                raise KeyError(f"{owner}: the input tensordict has no {key!r} entry")
            expected = self.env.full_observation_spec[key].shape[-1:]
            if x.shape[-1:] != expected:
                raise ValueError(f"{owner}: {key!r} has shape {tuple(x.shape)}, expected (..., {expected[0]})")
            if not torch.isfinite(x).all():
                raise ValueError(f"{owner}: {key!r} contains NaN/inf; cannot plan from a non-finite state")
        return tensordict.select(*self.observation_keys).reshape(-1).to(self.env_device)
