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
        if not (tensordict.batch_dims == 2 and tensordict.batch_size[0] == L or tensordict.batch_dims == 1):
            raise ValueError(
                f"EnsembleLoss: batch size {tuple(tensordict.batch_size)}, expected (B,) or (L={L}, B)"
            )
        model._check(obs, act)
        loss, mse = self.normalized_loss(model.network_input(obs, act), model.normalized_target(obs, nxt))
        return TensorDict({"loss_model": loss, "mse": mse.detach()}, batch_size=[])

    def normalized_loss(self, inputs: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The loss on the network's own input and target, with no tensordict on the way.

        Args:
            inputs: ``(L, B, d_s + d_a)`` one minibatch per member, or ``(B, d_s + d_a)`` shared,
                as :meth:`EnsembleWorldModel.network_input` makes them.
            target: ``(L, B, d_s)`` or ``(B, d_s)``, :meth:`EnsembleWorldModel.normalized_target`.

        Returns:
            ``loss_model`` (a scalar: the members' mean losses summed) and ``mse`` (the mean
            normalized squared error over members). Under ``torch.autocast`` only the hidden
            layers' matmuls run in the reduced dtype: the output head and the loss run in fp32.
        """
        model = self.world_model
        L = model.ensemble_size
        mean, logvar = model.network(inputs)
        if target.dim() == 2:
            target = target.expand(L, *target.shape)
        sq = (mean - target).square()
        mse = sq.mean()
        if self.loss_type == "mse":
            return sq.mean(dim=(1, 2)).sum(), mse
        loss = (sq * torch.exp(-logvar) + logvar).mean(dim=(1, 2)).sum()
        return loss + self.logvar_bound_coef * (model.max_logvar.sum() - model.min_logvar.sum()), mse
