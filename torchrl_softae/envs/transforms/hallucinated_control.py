"""Hallucinated control [eta] for optimistic planning (SoftAE, H-UCRL; Curi et al. 2020)."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded, Composite
from torchrl.envs.transforms import Transform

from torchrl_softae.modules.planners.contract import PlanningTransform

__all__ = ["HallucinatedControl", "RealActionPolicy", "DEFAULT_BETA"]

#: the confidence-set width [beta] of the paper (Table S6, every robot)
DEFAULT_BETA = 2.0


class HallucinatedControl(Transform, PlanningTransform):
    """Widens the action from ``a`` (d_a) to ``[a, eta]`` (d_a + d_s) with ``eta in [-1, 1]^{d_s}``.

    On the way in (``inv``) the planner's action is split: the first d_a entries go to
    ``"action"``, the last d_s become the hallucinated control ``"eta" = beta * eta`` in
    ``[-beta, beta]^{d_s}``, which an optimistic :class:`~torchrl_softae.envs.EnsembleModelEnv`
    turns into ``s' = mu + sigma * eta`` -- any dynamics in the confidence set
    ``[mu +- beta sigma]`` (paper eq. (exploration_optimistic_dyn)). The planner thus optimizes
    ``a`` and ``eta`` jointly. Only the model env ever sees ``eta``: wrap the planner with
    :meth:`policy_for_real_env` to act on the real system.

    Args:
        beta (float): confidence-set width [beta]. Default :data:`DEFAULT_BETA` = 2.0 (paper, Table S6).
        action_key, eta_key: the model env's action entries.

    Examples:
        >>> env = TransformedEnv(EnsembleModelEnv(EnsembleWorldModel(3, 1), mode="optimistic"),
        ...                      Compose(HallucinatedControl(beta=2.0), UncertaintyReward()))
        >>> env.action_spec.shape  # [a (1), eta (3)]
        torch.Size([4])
    """

    def __init__(self, beta: float = DEFAULT_BETA, action_key: str = "action", eta_key: str = "eta"):
        if not isinstance(beta, (int, float)) or not beta >= 0 or beta != beta or beta == float("inf"):
            raise ValueError(f"HallucinatedControl: beta={beta!r}, expected a finite number >= 0")
        super().__init__(in_keys_inv=[action_key], out_keys_inv=[action_key, eta_key])
        self.beta = float(beta)
        self.action_key = action_key
        self.eta_key = eta_key
        self.action_dim: int | None = None
        self.state_dim: int | None = None

    def transform_input_spec(self, input_spec: Composite) -> Composite:
        input_spec = input_spec.clone()
        actions = input_spec["full_action_spec"]
        if self.eta_key not in actions.keys():
            raise KeyError(
                f"HallucinatedControl needs an env with a {self.eta_key!r} action entry, "
                "i.e. EnsembleModelEnv(mode='optimistic')"
            )
        act, eta = actions[self.action_key], actions[self.eta_key]
        if not isinstance(act, Bounded):
            raise TypeError(f"HallucinatedControl needs a Bounded action spec, got {type(act).__name__}")
        self.action_dim, self.state_dim = act.shape[-1], eta.shape[-1]
        batch = act.shape[:-1]
        low = torch.cat([act.space.low, -torch.ones(*batch, self.state_dim, dtype=act.dtype, device=act.device)], -1)
        high = torch.cat([act.space.high, torch.ones(*batch, self.state_dim, dtype=act.dtype, device=act.device)], -1)
        del actions[self.eta_key]
        actions[self.action_key] = Bounded(low, high, (*batch, self.action_dim + self.state_dim), dtype=act.dtype, device=act.device)
        input_spec["full_action_spec"] = actions
        return input_spec

    def _resolve_dims(self) -> None:
        """Read d_a and d_s off the env below this transform (specs are computed lazily)."""
        if self.action_dim is None:
            parent = self.parent
            if parent is None:
                raise RuntimeError("HallucinatedControl is not attached to an env yet")
            self.transform_input_spec(parent.input_spec)

    def split(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(*B, d_a + d_s)`` -> real action ``(*B, d_a)`` and ``beta * eta`` ``(*B, d_s)``."""
        self._resolve_dims()
        expected = self.action_dim + self.state_dim
        if action.shape[-1] != expected:
            raise ValueError(
                f"HallucinatedControl: action has shape {tuple(action.shape)}, expected (..., {expected}) "
                f"= d_a {self.action_dim} + d_s {self.state_dim}"
            )
        return action[..., : self.action_dim], self.beta * action[..., self.action_dim :]

    def plan_action(self, entries: dict) -> dict:
        action, eta = self.split(entries[self.action_key])
        return {**entries, self.action_key: action, self.eta_key: eta}

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        action, eta = self.split(tensordict.get(self.action_key))
        tensordict.set(self.action_key, action)
        tensordict.set(self.eta_key, eta)
        return tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return tensordict_reset

    def policy_for_real_env(self, planner: TensorDictModuleBase) -> RealActionPolicy:
        """A policy for the real env: runs ``planner`` and keeps the first d_a action dims."""
        self._resolve_dims()
        return RealActionPolicy(planner, self.action_dim, self.action_key)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(beta={self.beta}, action_dim={self.action_dim}, state_dim={self.state_dim})"


class RealActionPolicy(TensorDictModuleBase):
    """Wraps a planner whose action is ``[a, eta]`` so that only ``a`` (first d_a dims) reaches the env."""

    def __init__(self, planner: TensorDictModuleBase, action_dim: int, action_key: str = "action"):
        super().__init__()
        self.planner = planner
        self.action_dim = action_dim
        self.action_key = action_key
        self.in_keys = list(getattr(planner, "in_keys", ["observation"]))
        self.out_keys = [action_key]

    def reset(self) -> None:
        if hasattr(self.planner, "reset"):
            self.planner.reset()

    def search_state(self) -> dict:
        """The wrapped planner's (:meth:`~torchrl_softae.modules.planners.common.SequencePlannerBase.search_state`)."""
        return self.planner.search_state()

    def load_search_state(self, state: dict) -> None:
        self.planner.load_search_state(state)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict = self.planner(tensordict)
        tensordict.set(self.action_key, tensordict.get(self.action_key)[..., : self.action_dim])
        return tensordict
