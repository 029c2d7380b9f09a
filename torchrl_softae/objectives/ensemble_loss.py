"""Joint maximum-likelihood loss for all ensemble members [paper eq. (fsvgd_updates)]."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import dispatch
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from torchrl_softae.modules.ensemble import EnsembleWorldModel

__all__ = ["EnsembleLoss"]


class EnsembleLoss(LossModule):
    """Trains the L members of an :class:`EnsembleWorldModel` in one batched pass.

    Every member regresses the normalized delta ``(s' - s - m) / v``. With ``loss_type="nll"``
    (default for probabilistic models) each member minimizes the Gaussian negative log-likelihood
    with its bounded log-variance, plus ``logvar_bound_coef * (sum max_logvar - sum min_logvar)``
    which keeps the soft bounds tight (PETS). ``loss_type="mse"`` is the paper's squared error
    ``N(NN(s, a), eps^2)``.

    The input tensordict either has batch ``(B,)`` (every member sees the same minibatch) or
    ``(L, B)``: member ``l`` trains on its own bootstrap/shuffled minibatch ``td[l]``.

    Returns a tensordict with ``loss_model`` (sum over members, to backpropagate) and the
    detached diagnostic ``mse`` (mean normalized squared error over members).
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys: ``observation`` [s], ``action`` [a], ``next_observation`` [s']."""

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        next_observation: NestedKey = ("next", "observation")

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys

    def __init__(
        self,
        world_model: EnsembleWorldModel,
        *,
        loss_type: str | None = None,
        logvar_bound_coef: float = 0.01,
    ):
        super().__init__()
        if not isinstance(world_model, EnsembleWorldModel):
            raise TypeError(f"EnsembleLoss expects an EnsembleWorldModel, got {type(world_model).__name__}")
        if loss_type is None:
            loss_type = "nll" if world_model.probabilistic else "mse"
        if loss_type not in ("nll", "mse"):
            raise ValueError(f"loss_type={loss_type!r}, expected one of 'nll', 'mse'")
        if loss_type == "nll" and not world_model.probabilistic:
            raise ValueError("loss_type='nll' needs a probabilistic EnsembleWorldModel (probabilistic=True)")
        self.world_model = world_model
        self.loss_type = loss_type
        self.logvar_bound_coef = logvar_bound_coef

    @property
    def in_keys(self):
        k = self.tensor_keys
        return [k.observation, k.action, k.next_observation]

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        k = self.tensor_keys
        model = self.world_model
        obs = tensordict.get(k.observation)
        act = tensordict.get(k.action)
        nxt = tensordict.get(k.next_observation)
        L = model.ensemble_size
        if tensordict.batch_dims == 2 and tensordict.batch_size[0] == L:
            per_member = True
        elif tensordict.batch_dims == 1:
            per_member = False
        else:
            raise ValueError(
                f"EnsembleLoss: batch size {tuple(tensordict.batch_size)}, expected (B,) or (L={L}, B)"
            )
        model._check(obs, act)
        target = model.normalized_target(obs, nxt)
        mean, logvar = model.normalized_members(obs, act)
        if not per_member:
            target = target.expand(L, *target.shape)
        sq = (mean - target).square()
        mse = sq.mean()
        if self.loss_type == "mse":
            loss = sq.mean(dim=(1, 2)).sum()
        else:
            loss = (sq * torch.exp(-logvar) + logvar).mean(dim=(1, 2)).sum()
            loss = loss + self.logvar_bound_coef * (model.max_logvar.sum() - model.min_logvar.sum())
        return TensorDict({"loss_model": loss, "mse": mse.detach()}, batch_size=[])
