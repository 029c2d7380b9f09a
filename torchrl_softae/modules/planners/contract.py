"""The planner/model-env contract: how an env scores whole action sequences for a planner.

It lives with the planners (what they need from an env); the model env implements it
(``torchrl_softae.envs.EnsembleModelEnv``), so the dependency runs one way: envs -> modules.

A planner (:class:`~torchrl_softae.modules.planners.ICEMPlanner`, ``MPPIPlanner``) never reaches
into a model env's attributes. If the env it plans in (or, behind TorchRL transforms, the base
env) is an :class:`ActionSequenceEvaluator`, the planner asks it, and only it, for

* how many particles a candidate needs (:meth:`~ActionSequenceEvaluator.particles_needed`: 1 when
  propagation is deterministic),
* which entries of the input describe the initial state (:attr:`~ActionSequenceEvaluator.state_keys`),
* the returns of a batch of action sequences (:meth:`~ActionSequenceEvaluator.evaluate_action_sequences`),
  in a given planning precision, with the rewards of the transforms stacked on top of it,
* the state of its own generator, if scoring draws from one (:meth:`~ActionSequenceEvaluator.generator_state`),
  so that a planner's ``search_state`` holds everything its next call depends on.

Any other batch-unlocked TorchRL env is planned over with TorchRL's generic ``env.rollout``
(:func:`rollout_returns`). This is the role of mbrl-lib's ``ModelEnv.evaluate_action_sequences``:
the model env owns how sequences are scored.
"""
from __future__ import annotations

import abc
import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

__all__ = ["ActionSequenceEvaluator", "PlanningTransform", "rollout_returns", "PLANNING_PRECISIONS"]

PLANNING_PRECISIONS = ("fp32", "bf16", "auto")


class ActionSequenceEvaluator(abc.ABC):
    """Mixin of envs that score action sequences themselves (see the module docstring)."""

    @property
    @abc.abstractmethod
    def state_keys(self) -> list:
        """Entries of a planner's input tensordict that make the initial state."""

    @abc.abstractmethod
    def particles_needed(self, requested: int) -> int:
        """Rollouts per candidate the env needs for ``requested`` particles (1 if deterministic)."""

    @abc.abstractmethod
    def evaluate_action_sequences(
        self,
        initial_state: TensorDictBase,
        action_sequences: torch.Tensor,
        *,
        num_particles: int,
        env: EnvBase | None = None,
        precision: str = "fp32",
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Predicted returns of action sequences.

        Args:
            initial_state: ``(B,)`` tensordict with :attr:`state_keys`.
            action_sequences: ``(B, N, H, d)``, each inside ``env``'s action spec.
            num_particles: rollouts per candidate (already reduced by :meth:`particles_needed`).
            env: the env whose reward is summed: this env, or a ``TransformedEnv`` over it (its
                transforms map actions and set the reward). Default: this env.
            precision: ``"fp32"``, ``"bf16"`` or ``"auto"`` for the model's hidden layers.
            generator: the caller's random generator (particle assignments, noise).

        Returns:
            ``(B, N)`` returns summed over the horizon and averaged over particles; a candidate
            whose return is NaN/inf gets ``-inf`` (it never wins).
        """

    def generator_state(self) -> torch.Tensor | None:
        """The state of the env's own random generator if scoring draws from it (besides the
        caller's ``generator``), for a planner's ``search_state``; ``None`` if it draws from none."""
        return None

    def set_generator_state(self, state: torch.Tensor) -> None:
        """Restore :meth:`generator_state`."""
        raise NotImplementedError(f"{type(self).__name__} scores without a generator of its own")


class PlanningTransform:
    """Mixin of TorchRL transforms that can also act on plain tensors, so that a model env may score
    sequences in a tight tensor loop (no TensorDict per step) when every transform of its stack is
    one. The transform's TorchRL methods and these two must agree (tested).
    """

    def plan_action(self, entries: dict) -> dict:
        """The action entries on their way to the model env (``{"action": (*B, d)}`` in).

        A model env calls it once for whole action sequences (``*B`` ending with the horizon), so
        it must map each step's action alone, as TorchRL's inverse transforms see one step."""
        return entries

    def plan_reward(self, observation: torch.Tensor, action: torch.Tensor, next_observation: torch.Tensor,
                    epistemic_std: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
        """The reward ``(*B, 1)`` after this transform, given the one before it (a new tensor: the
        arguments are read only, and the model env's own zero reward may be one expanded value).

        A model env may call it once for every step of a rollout (``*B`` then starting with the
        horizon, each argument its steps' values stacked), so it must compute each step's reward
        from that step's arguments alone, as TorchRL's transforms see one step."""
        return reward


class _ReplayActions(TensorDictModuleBase):
    """A policy for ``env.rollout`` that plays precomputed actions ``(*B, H, d)`` step by step."""

    def __init__(self, actions: torch.Tensor, action_key="action"):
        super().__init__()
        self.actions, self.action_key, self.t = actions, action_key, 0
        self.in_keys, self.out_keys = [], [action_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set(self.action_key, self.actions[..., self.t, :])
        self.t += 1
        return tensordict


def rollout_returns(
    env: EnvBase,
    initial_state: TensorDictBase,
    action_sequences: torch.Tensor,
    num_particles: int = 1,
    reward_key=("next", "reward"),
    action_key="action",
) -> torch.Tensor:
    """Returns of action sequences in any batch-unlocked TorchRL env, through ``env.rollout``.

    Shapes as in :meth:`ActionSequenceEvaluator.evaluate_action_sequences`; a step that is done
    ends the sum for that rollout (TorchRL's rollout keeps stepping the batch, so the reward after
    ``done`` is masked out here).
    """
    B, N, H, d = action_sequences.shape
    P = num_particles
    # entries a reset would have written (zeros), then the given initial state over them
    td = env.full_observation_spec.zero((B, N, P))
    td.update(env.full_state_spec.zero((B, N, P))).update(env.full_done_spec.zero((B, N, P)))
    td.update(initial_state.reshape(B, 1, 1).expand(B, N, P))
    acts = action_sequences.unsqueeze(2).expand(B, N, P, H, d)
    traj = env.rollout(H, _ReplayActions(acts, action_key), tensordict=td, auto_reset=False,
                       break_when_any_done=False, return_contiguous=True)
    r = traj.get(reward_key).reshape(B, N, P, H, -1)[..., :1].float()
    done = traj.get(("next", "done"), None)
    if done is not None:
        # a step counts while none of the steps before it was done
        alive = (~done.reshape(B, N, P, H, 1)).long().cumprod(-2).roll(1, -2)
        alive[..., 0, :] = 1
        r = torch.where(alive.bool(), r, torch.zeros_like(r))
    ret = r.sum((-2, -1)).mean(-1)
    return torch.where(torch.isfinite(ret), ret, torch.full_like(ret, -math.inf))
