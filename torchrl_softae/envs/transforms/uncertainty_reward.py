"""The exploration objective: reward = ||sigma(s, a)|| [paper eq. (exploration_op)]."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from torchrl_softae.modules.planners.contract import PlanningTransform

__all__ = ["UncertaintyReward"]


class UncertaintyReward(Transform, PlanningTransform):
    """Sets ``reward = || sigma / scale ||_ord`` from the model env's epistemic std.

    Summed over the planning horizon by the planner, this is the active-exploration objective
    ``J_n = sum_t ||sigma_n(s_t, a_t)||``. No task reward is involved.

    Args:
        ord (float): the vector norm (2 = Euclidean, as in the paper; 1; ``float("inf")``).
        scale (Tensor, optional): ``(d_s,)`` per-dimension divisor, e.g. the data's state std so
            that dimensions in different units (positions vs quaternions) count alike. Update it
            in place with :meth:`set_scale` after each retraining.
        in_key: where sigma is read. Default ``"epistemic_std"``.
        out_key: where the reward is written. Default ``"reward"``.

    Examples:
        >>> env = TransformedEnv(EnsembleModelEnv(EnsembleWorldModel(3, 1)), UncertaintyReward())
        >>> td = env.reset(TensorDict({"observation": torch.zeros(2, 3)}, [2]))
        >>> env.step(td.set("action", torch.zeros(2, 1)))["next", "reward"].shape  # ||sigma||
        torch.Size([2, 1])
    """

    def __init__(self, ord: float = 2.0, scale: torch.Tensor | None = None, in_key="epistemic_std", out_key="reward"):
        if not (isinstance(ord, (int, float)) and ord > 0):
            raise ValueError(f"UncertaintyReward: ord={ord!r}, expected a positive number (1, 2, inf, ...)")
        super().__init__(in_keys=[in_key], out_keys=[out_key])
        self.ord = float(ord)
        self.register_buffer("scale", None if scale is None else torch.as_tensor(scale, dtype=torch.float32).clone())

    @torch.no_grad()
    def set_scale(self, scale: torch.Tensor | None) -> None:
        """Replace the per-dimension divisor (values must be positive and finite)."""
        if scale is not None:
            scale = torch.as_tensor(scale, dtype=torch.float32)
            if not (torch.isfinite(scale).all() and (scale > 0).all()):
                raise ValueError(f"UncertaintyReward: scale must be positive and finite, got {scale}")
        self.scale = None if scale is None else scale.clone()

    def reward_from_sigma(self, sigma: torch.Tensor) -> torch.Tensor:
        """``(*B, d_s)`` epistemic std -> ``(*B, 1)`` reward."""
        if self.scale is not None:
            if self.scale.shape[-1] != sigma.shape[-1]:
                raise ValueError(f"UncertaintyReward: scale has {self.scale.shape[-1]} dims, sigma has {sigma.shape[-1]}")
            sigma = sigma / self.scale.to(sigma.device)
        # one op for every ord (cheaper than square, sum and sqrt right after a network call)
        return torch.linalg.vector_norm(sigma, ord=self.ord, dim=-1, keepdim=True)

    def plan_reward(self, observation, action, next_observation, epistemic_std, reward):
        return self.reward_from_sigma(epistemic_std)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        sigma = next_tensordict.get(self.in_keys[0], None)
        if sigma is None:
            raise KeyError(
                f"UncertaintyReward needs {self.in_keys[0]!r} in the step output: use it on an EnsembleModelEnv"
            )
        next_tensordict.set(self.out_keys[0], self.reward_from_sigma(sigma))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return tensordict_reset

    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        reward_spec[self.out_keys[0]] = Unbounded((*reward_spec.shape, 1), device=reward_spec.device)
        return reward_spec

    def __repr__(self) -> str:
        return f"{type(self).__name__}(ord={self.ord}, scaled={self.scale is not None})"
