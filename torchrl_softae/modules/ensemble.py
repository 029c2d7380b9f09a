"""Probabilistic ensemble world model [mu_n, sigma_n] (paper: "Learning Uncertainty Aware Dynamics").

All L members live in stacked weight tensors of shape ``(L, in, out)`` and run in one
``torch.baddbmm`` per layer: there is no Python loop over members. Each member ``l`` predicts the
normalized state *delta* ``(s' - s - m) / v`` from the normalized input ``(s, a)`` together with a
bounded log-variance (PETS soft bounds). In original units

    member mean     m_l(s, a) = s + m + v * NN_l(s, a)                  (L, *B, d_s)
    mean            mu(s, a)  = 1/L sum_l m_l(s, a)                     [mu]
    epistemic std   sigma     = sqrt(1/(L-1) sum_l (m_l - mu)^2)        [sigma]
    aleatoric std   sqrt(1/L sum_l var_l(s, a))                         [the noise w_t]
    SoftAE step     s' = mu + sigma * (beta eta)                        [eta: hallucinated control]

This file is the maths in plain torch. At inference a model also has an engine
(``model.engine``, :mod:`torchrl_softae.modules.engine`, attached where :mod:`torchrl_softae.modules`
builds it) that runs the same network and formulas faster: measured paths, packed weights,
compiled kernels, planning rollouts.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torch.nn import functional as F

__all__ = ["EnsembleLinear", "Normalizer", "EnsembleWorldModel", "KERNEL_CHOICES", "attach_engine",
           "ensemble_moments", "ensemble_std", "symlog", "symexp"]

#: ``kernels=`` of a model: ``"auto"`` lets its engine run compiled kernels where they apply and
#: measured faster, ``"torch"`` keeps it to torch's own ops
KERNEL_CHOICES = ("auto", "torch")

#: ``(model, kernels) -> engine``, set by :func:`attach_engine` (``None``: models run plain torch)
_ENGINE_FACTORY = None


def attach_engine(factory) -> None:
    """Gives every model built from now on ``model.engine = factory(model, kernels)``, which runs
    its inference (:meth:`EnsembleWorldModel.network_output` without autograd, and the moments).
    :mod:`torchrl_softae.modules` attaches :class:`~torchrl_softae.modules.engine.InferenceEngine`."""
    global _ENGINE_FACTORY
    _ENGINE_FACTORY = factory


def symlog(x: torch.Tensor) -> torch.Tensor:
    """``sign(x) log(1 + |x|)``: compresses large magnitudes, identity-like near 0 (DreamerV3)."""
    return torch.sign(x) * torch.log1p(x.abs())


def symexp(y: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`symlog`: ``sign(y) (exp(|y|) - 1)``."""
    return torch.sign(y) * torch.expm1(y.abs())


def ensemble_moments(members: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """mu [mu] and the epistemic std sigma [sigma] over the leading member dim of ``members``
    ``(L, ...)``: the members' mean and their unbiased std, each ``(...)``."""
    mu = members.mean(0)
    return mu, ensemble_std(members, mu)


def ensemble_std(members: torch.Tensor, mean: torch.Tensor | None = None) -> torch.Tensor:
    """Unbiased std over the leading member dim of ``members`` (L, ...).

    The explicit formula, not ``Tensor.std(0)``: on the CPU that reduction over the member dim is
    slow enough to double a plan's time.
    """
    if mean is None:
        mean = members.mean(0)
    n = members.shape[0]
    return (members - mean).square_().sum(0).div_(max(n - 1, 1)).sqrt_()


class EnsembleLinear(nn.Module):
    """``L`` independent affine maps applied in one batched matmul.

    Args:
        ensemble_size (int): number of members L.
        in_features, out_features (int): sizes of each member's layer.

    Shapes: input ``(L, N, in)`` (or ``(N, in)``, shared by all members), output ``(L, N, out)``.
    """

    def __init__(self, ensemble_size: int, in_features: int, out_features: int, device=None, dtype=None):
        super().__init__()
        self.ensemble_size = ensemble_size
        self.in_features = in_features
        self.out_features = out_features
        factory = {"device": device, "dtype": dtype}
        self.weight = nn.Parameter(torch.empty(ensemble_size, in_features, out_features, **factory))
        self.bias = nn.Parameter(torch.empty(ensemble_size, 1, out_features, **factory))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        # nn.Linear's default, drawn independently for every member: the members' different
        # initializations are what makes their disagreement an epistemic uncertainty.
        bound = 1.0 / math.sqrt(self.in_features)
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() == 2:  # shared input: one (N, in) @ (L, in, out) broadcast matmul
            return torch.matmul(x, self.weight) + self.bias
        return torch.baddbmm(self.bias, x, self.weight)

    def extra_repr(self) -> str:
        return f"ensemble_size={self.ensemble_size}, in_features={self.in_features}, out_features={self.out_features}"


class Normalizer(nn.Module):
    """Per-dimension affine normalizer ``(x - loc) / scale`` fitted from data; saved in state_dict."""

    def __init__(self, size: int, eps: float = 1e-6, device=None):
        super().__init__()
        self.eps = eps
        self.register_buffer("loc", torch.zeros(size, device=device))
        self.register_buffer("scale", torch.ones(size, device=device))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool, device=device))

    @torch.no_grad()
    def fit(self, data: torch.Tensor) -> None:
        data = data.reshape(-1, data.shape[-1]).to(self.loc)
        if data.shape[0] < 2:
            raise ValueError(f"Normalizer.fit needs at least 2 rows, got data of shape {tuple(data.shape)}")
        if not torch.isfinite(data).all():
            raise ValueError("Normalizer.fit got NaN/inf values; clean the data before fitting")
        std = data.std(0)
        self.loc.copy_(data.mean(0))
        # A constant dimension keeps unit scale rather than blowing up its normalized values.
        self.scale.copy_(torch.where(std > self.eps, std, torch.ones_like(std)))
        self.fitted.fill_(True)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.loc) / self.scale

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.scale + self.loc


class EnsembleWorldModel(TensorDictModuleBase):
    """L-member probabilistic MLP ensemble predicting the next state [mu_n, sigma_n].

    Args:
        observation_dim (int): d_s.
        action_dim (int): d_a.
        ensemble_size (int): L, number of members. Default 5 (paper, Table S6).
        num_cells (int): hidden width. Default 256.
        depth (int): number of hidden layers. Default 4.
        activation_class: hidden activation. Default ``nn.SiLU``.
        probabilistic (bool): if ``True`` each member also predicts a bounded log-variance
            (Gaussian NLL training, aleatoric noise); otherwise the aleatoric std is zero and the
            model is trained with squared error as in the paper. Default ``True``.
        min_logvar, max_logvar (float): initial soft bounds of the normalized log-variance.
        in_keys: keys of the state ``s`` (d_s) and action ``a`` (d_a). Default ``("observation", "action")``.
        out_keys: keys of the next-state mean [mu], epistemic std [sigma] and aleatoric std.
            Default ``("loc", "epistemic_std", "aleatoric_std")``.
        symlog_observations (bool): model the state in symlog space (:func:`symlog` before the
            input normalizer, :func:`symexp` after the prediction), for states whose dimensions
            span orders of magnitude; predictions, sigma and the aleatoric std (first order) are
            returned in original units. Default ``False``.
        device: where parameters and normalizers are created (TorchRL convention; ``.to()`` later
            works too).
        kernels: ``"auto"`` or ``"torch"`` (:data:`KERNEL_CHOICES`): whether the model's engine may
            run compiled kernels; ``SOFTAE_KERNELS=0`` turns them off in the whole process.

    Shapes: ``observation`` ``(*B, d_s)``, ``action`` ``(*B, d_a)``; all outputs ``(*B, d_s)``.

    Examples:
        >>> model = EnsembleWorldModel(3, 1, ensemble_size=5)
        >>> td = TensorDict({"observation": torch.randn(8, 3), "action": torch.randn(8, 1)}, [8])
        >>> model(td)["epistemic_std"].shape
        torch.Size([8, 3])
    """

    def __init__(
        self,
        observation_dim: int,
        action_dim: int,
        ensemble_size: int = 5,
        num_cells: int = 256,
        depth: int = 4,
        activation_class: type[nn.Module] = nn.SiLU,
        probabilistic: bool = True,
        min_logvar: float = -10.0,
        max_logvar: float = 0.5,
        in_keys: Sequence = ("observation", "action"),
        out_keys: Sequence = ("loc", "epistemic_std", "aleatoric_std"),
        symlog_observations: bool = False,
        device=None,
        kernels: str = "auto",
    ):
        if kernels not in KERNEL_CHOICES:  # refused before anything is built
            raise ValueError(f"kernels={kernels!r}: expected one of {', '.join(KERNEL_CHOICES)}")
        for name, value, low in (
            ("observation_dim", observation_dim, 1),
            ("action_dim", action_dim, 1),
            ("ensemble_size", ensemble_size, 2),
            ("num_cells", num_cells, 1),
            ("depth", depth, 1),
        ):
            if not isinstance(value, int) or value < low:
                raise ValueError(f"EnsembleWorldModel: {name}={value!r}, expected an int >= {low}")
        if len(in_keys) != 2 or len(out_keys) != 3:
            raise ValueError(f"in_keys must be (state, action) and out_keys (loc, epistemic_std, aleatoric_std), got {in_keys}, {out_keys}")
        super().__init__()
        self.in_keys = list(in_keys)
        self.out_keys = list(out_keys)
        self.observation_dim = observation_dim
        self.action_dim = action_dim
        self.ensemble_size = ensemble_size
        self.probabilistic = probabilistic
        self.symlog_observations = bool(symlog_observations)
        self.kernels = kernels
        sizes = [observation_dim + action_dim] + [num_cells] * depth
        out = 2 * observation_dim if probabilistic else observation_dim
        self.layers = nn.ModuleList(
            [EnsembleLinear(ensemble_size, i, o, device=device) for i, o in zip(sizes[:-1], sizes[1:])]
            + [EnsembleLinear(ensemble_size, sizes[-1], out, device=device)]
        )
        self.activation = activation_class()
        self.min_logvar = nn.Parameter(torch.full((1, observation_dim), float(min_logvar), device=device))
        self.max_logvar = nn.Parameter(torch.full((1, observation_dim), float(max_logvar), device=device))
        self.input_normalizer = Normalizer(observation_dim + action_dim, device=device)
        self.output_normalizer = Normalizer(observation_dim, device=device)
        #: the inference engine (``None``: plain torch at inference too)
        self.engine = None if _ENGINE_FACTORY is None else _ENGINE_FACTORY(self, kernels)

    def _apply(self, fn, recurse=True):  # .to(), .double(), ...: new parameters, the engine's weights stale
        if self.engine is not None:
            self.engine.clear_inference_cache()
        return super()._apply(fn, recurse)

    # ------------------------------------------------------------------ data fitting
    @torch.no_grad()
    def fit_normalizers(self, observation: torch.Tensor, action: torch.Tensor, next_observation: torch.Tensor) -> None:
        """Fit input (s, a) and output (s' - s) normalizers from transitions of shape (N, d)
        (in symlog space with ``symlog_observations``)."""
        self._check(observation, action)
        obs, nxt = self._to_model_space(observation), self._to_model_space(next_observation)
        self.input_normalizer.fit(torch.cat([obs, action], -1))
        self.output_normalizer.fit(nxt - obs)

    def _to_model_space(self, state: torch.Tensor) -> torch.Tensor:
        return symlog(state) if self.symlog_observations else state

    def normalized_target(self, observation: torch.Tensor, next_observation: torch.Tensor) -> torch.Tensor:
        """The training target: the normalized state delta in the model's space, ``(..., d_s)``."""
        return self.output_normalizer.normalize(self._to_model_space(next_observation) - self._to_model_space(observation))

    # ------------------------------------------------------------------ input validation
    def check_dtype(self, key: str, x: torch.Tensor) -> None:
        """A TypeError naming ``key``'s dtype and the fix where ``x`` is not of the parameters' dtype."""
        dtype = self.layers[0].weight.dtype
        if x.dtype != dtype:
            raise TypeError(f"EnsembleWorldModel: {key!r} is {x.dtype}, the model's parameters {dtype}: cast the "
                            "data (TorchRL's DoubleToFloat transform for an env with float64 specs) or the "
                            f"model (model.to({x.dtype}))")

    def _check(self, observation: torch.Tensor, action: torch.Tensor) -> None:
        for key, x, d in (
            (self.in_keys[0], observation, self.observation_dim),
            (self.in_keys[1], action, self.action_dim),
        ):
            if not isinstance(x, torch.Tensor):
                raise TypeError(f"EnsembleWorldModel: {key!r} must be a tensor, got {type(x).__name__}")
            if x.shape[-1:] != (d,):
                raise ValueError(f"EnsembleWorldModel: {key!r} has shape {tuple(x.shape)}, expected (..., {d})")
            self.check_dtype(key, x)
            if not torch.isfinite(x).all():
                bad = (~torch.isfinite(x)).nonzero()[0].tolist()
                raise ValueError(f"EnsembleWorldModel: {key!r} contains NaN/inf (first at index {bad})")
        if observation.shape[:-1] != action.shape[:-1]:
            raise ValueError(f"EnsembleWorldModel: batch shapes differ: {self.in_keys[0]!r} {tuple(observation.shape)} "
                             f"vs {self.in_keys[1]!r} {tuple(action.shape)}")

    def network(
        self, x: torch.Tensor, with_logvar: bool = True, bound_logvar: bool = True, dtype: torch.dtype | None = None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Raw ensemble on normalized inputs.

        Args:
            x: ``(N, d_s + d_a)`` shared by all members, or ``(L, N, d_s + d_a)`` one batch per member.
            with_logvar: compute the log-variance head; planning with deterministic propagation
                does not need it and skips half of the output layer.
            bound_logvar: apply the soft bounds (``False``: raw head output, to bound only the
                entries actually used).
            dtype: the hidden layers' dtype at inference (``torch.bfloat16`` to plan in bf16;
                ``None``: fp32), as the engine runs them.

        Returns:
            normalized delta mean ``(L, N, d_s)`` and bounded normalized log-variance (same shape;
            ``None`` if not probabilistic or not requested).
        """
        d = self.observation_dim
        y = self.network_output(x, with_logvar, dtype).float()
        if not (self.probabilistic and with_logvar):
            return y[..., :d], None
        return y[..., :d], (self._bound_logvar(y[..., d:]) if bound_logvar else y[..., d:])

    def network_output(self, x: torch.Tensor, with_logvar: bool = True, dtype: torch.dtype | None = None) -> torch.Tensor:
        """Raw ensemble on normalized inputs: the last layer's output ``(L, N, C)``. Columns
        ``[:d_s]`` are the normalized delta means, ``[d_s:]`` the raw log-variances (when
        probabilistic; without ``with_logvar`` the engine may leave them out). Every prediction goes
        through here: :meth:`network`, :meth:`predict_members` and :meth:`predict_moments`; without
        autograd, by the engine, its hidden layers in ``dtype`` (``None``: fp32; without an engine
        the weights' dtype)."""
        if self.engine is not None and not torch.is_grad_enabled():
            return self.engine.network_output(x, with_logvar, dtype)
        *hidden, last = self.layers  # (unpacked: slicing a ModuleList builds a new module)
        for layer in hidden:
            x = self.activation(layer(x))
        # The output head (mean and log-variance) stays in the weights' dtype under autocast:
        # in bf16 its rounding cost validation NLL on the arm (benchmarks/training_precision.py).
        with torch.autocast(x.device.type, enabled=False):
            return last(x.to(last.weight.dtype))

    def _bound_logvar(self, logvar: torch.Tensor) -> torch.Tensor:
        """PETS soft bounds: smooth clamp of the log-variance into [min_logvar, max_logvar]."""
        hi, lo = self.max_logvar.to(logvar.dtype), self.min_logvar.to(logvar.dtype)
        logvar = hi - F.softplus(hi - logvar)
        return lo + F.softplus(logvar - lo)

    def network_input(self, observation: torch.Tensor, action: torch.Tensor,
                      action_normalized: bool = False) -> torch.Tensor:
        """The network's input ``(..., d_s + d_a)`` at ``(s, a)``: states in the model's space and
        actions, normalized column by column (the actions already, with ``action_normalized``)."""
        if not action_normalized:
            action = self.normalized_actions(action)
        return torch.cat([self._normalized_states(observation), action], -1)

    def _normalized_states(self, observation: torch.Tensor) -> torch.Tensor:
        """States ``(..., d_s)`` as the network takes them (its input's state columns)."""
        d = self.observation_dim
        norm = self.input_normalizer
        return (self._to_model_space(observation) - norm.loc[:d]) / norm.scale[:d]

    def normalized_actions(self, action: torch.Tensor) -> torch.Tensor:
        """Actions ``(..., d_a)`` as the network takes them (its input's action columns, normalized).

        A planner knows its candidates' actions for the whole horizon: normalized once, they are
        passed to :meth:`predict_moments` / :meth:`predict_members` with ``action_normalized=True``
        at every step (the same values as normalizing them there)."""
        d = self.observation_dim
        norm = self.input_normalizer
        return (action - norm.loc[d:]) / norm.scale[d:]

    def predict_members(
        self, observation: torch.Tensor, action: torch.Tensor, with_aleatoric: bool = True,
        member_index: torch.Tensor | None = None, *, action_normalized: bool = False, dtype: torch.dtype | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Every member's next-state mean and aleatoric std in original units.

        Args:
            observation: ``(*B, d_s)``; action: ``(*B, d_a)``.
            with_aleatoric: also compute the aleatoric std (else ``None`` is returned for it).
            member_index: ``(*B,)`` member per row (trajectory sampling): the aleatoric std is then
                computed for that member only and returned with shape ``(*B, d_s)``.
            action_normalized: ``action`` is :meth:`normalized_actions` of the actions.
            dtype: the hidden layers' dtype (:meth:`network`).

        Returns:
            ``(L, *B, d_s)`` member means [NN_l(s, a)] and ``(L, *B, d_s)`` aleatoric stds.
        """
        batch = observation.shape[:-1]
        obs = observation.reshape(-1, self.observation_dim)
        act = action.reshape(-1, self.action_dim)
        raw = self.network_output(self.network_input(obs, act, action_normalized), with_aleatoric, dtype)
        return self._members_from_output(raw, obs, batch, with_aleatoric, member_index)

    def _members_from_output(self, raw, obs, batch, with_aleatoric, member_index):
        """:meth:`predict_members` from the raw network output ``raw`` ``(L, N, C)`` at the flat
        states ``obs`` ``(N, d_s)``."""
        d = self.observation_dim
        y = raw.float()
        mean = y[..., :d]
        logvar = y[..., d:] if (self.probabilistic and with_aleatoric) else None
        if logvar is not None and member_index is None:
            logvar = self._bound_logvar(logvar)
        out = self.output_normalizer
        members = torch.addcmul(self._to_model_space(obs) + out.loc, out.scale, mean)
        # symexp'(y) = exp(|y|): the aleatoric std maps back to original units to first order
        stretch = members.abs().exp() if self.symlog_observations else None
        if self.symlog_observations:
            members = symexp(members)
        shape = (self.ensemble_size, *batch, d)
        if not with_aleatoric:
            return members.reshape(shape), None
        if logvar is None:  # deterministic members: no aleatoric noise
            ale = torch.zeros_like(members)
            if member_index is not None:
                return members.reshape(shape), ale[0].reshape(*batch, d)
        elif member_index is not None:
            idx = member_index.reshape(1, -1, 1).expand(1, *logvar.shape[1:])
            ale = self._aleatoric_std(self._bound_logvar(logvar.gather(0, idx).squeeze(0)))
            if stretch is not None:
                ale = ale * stretch.gather(0, idx).squeeze(0)
            return members.reshape(shape), ale.reshape(*batch, d)
        else:
            ale = self._aleatoric_std(logvar)
            if stretch is not None:
                ale = ale * stretch
        return members.reshape(shape), ale.reshape(shape)

    def _aleatoric_std(self, logvar: torch.Tensor) -> torch.Tensor:
        """The aleatoric std in the model's units from a bounded normalized log-variance."""
        return self.output_normalizer.scale * (0.5 * logvar).exp()

    def predict_moments(
        self, observation: torch.Tensor, action: torch.Tensor, with_aleatoric: bool = False,
        member_index: torch.Tensor | None = None, *, action_normalized: bool = False,
        eta: torch.Tensor | None = None, dtype: torch.dtype | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """What propagation needs from the ensemble at ``(s, a)``, without the member means.

        Args:
            observation: ``(*B, d_s)``; action: ``(*B, d_a)``.
            with_aleatoric: also return the aleatoric std.
            member_index: ``(*B,)`` member per row (trajectory sampling), or ``None``.
            action_normalized: ``action`` is :meth:`normalized_actions` of the actions.
            eta: ``(*B, d_s)`` the hallucinated control with beta applied: the first output is then
                the optimistic next state ``mu + sigma * eta`` (:meth:`optimistic_step`).
            dtype: the hidden layers' dtype (:meth:`network`).

        Returns:
            ``mu`` [mu] and ``sigma`` [sigma] ``(*B, d_s)``; the mean of member ``member_index``
            ``(*B, d_s)`` (``None`` without it); the aleatoric std ``(*B, d_s)``: that member's, or
            without ``member_index`` the root mean square over the members (``None`` unless
            ``with_aleatoric``).

        The formulas are :meth:`moments_from_output`'s (the engine's kernel where it applies).
        """
        d = self.observation_dim
        batch = observation.shape[:-1]
        obs = observation.reshape(-1, d)
        act = action.reshape(-1, self.action_dim)
        if member_index is not None:
            member_index = member_index.reshape(-1)
        raw = self.network_output(self.network_input(obs, act, action_normalized), with_aleatoric, dtype)
        eta = None if eta is None else eta.reshape(-1, d)
        mu, sigma, member_mean, ale = self.moments_from_output(raw, obs, with_aleatoric, member_index, eta)
        shape = (*batch, d)
        return (mu.reshape(shape), sigma.reshape(shape), None if member_mean is None else member_mean.reshape(shape),
                None if ale is None else ale.reshape(shape))

    def moments_from_output(self, raw, obs, with_aleatoric=False, member_index=None, eta=None, next_input=None):
        """mu [mu], sigma [sigma], the mean of member ``member_index`` and the aleatoric std from the
        raw network output ``raw`` ``(L, N, C)`` at the flat states ``obs`` ``(N, d_s)``; flat
        ``(N, d_s)`` results (:meth:`predict_moments`). With ``eta`` ``(N, d_s)`` (beta applied) the
        first is the optimistic next state ``mu + sigma * eta`` (SoftAE, H-UCRL); with
        ``next_input`` ``(N, d_s + d_a)`` its state columns receive that next state, normalized."""
        if self.engine is not None:
            fused = self.engine.moments(raw, obs, with_aleatoric, member_index, eta, next_input)
            if fused is not None:
                return fused
        d = self.observation_dim
        members, ale = self._members_from_output(raw, obs, (obs.shape[0],), with_aleatoric, member_index)
        mu, sigma = ensemble_moments(members)
        member_mean = None
        if member_index is not None:
            member_mean = members.gather(0, member_index.reshape(1, -1, 1).expand(1, *mu.shape)).squeeze(0)
        elif ale is not None:
            ale = ale.square().mean(0).sqrt()
        if eta is not None:
            mu = self.optimistic_step(mu, sigma, eta)
        if next_input is not None:
            next_input[:, :d] = self._normalized_states(mu)
        return mu, sigma, member_mean, ale

    @staticmethod
    def optimistic_step(mu: torch.Tensor, sigma: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
        """SoftAE's and H-UCRL's next state ``s' = mu + sigma * eta`` [eta the hallucinated control
        with beta applied, ``beta * eta`` in the paper]; any broadcastable shapes."""
        return torch.addcmul(mu, sigma, eta)

    def predict(
        self, observation: torch.Tensor, action: torch.Tensor, check: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Returns ``(mu, sigma, aleatoric_std, members)``; shapes ``(*B, d_s)`` and ``(L, *B, d_s)``."""
        if check:
            self._check(observation, action)
        members, ale = self.predict_members(observation, action)
        mu, sigma = ensemble_moments(members)
        aleatoric = ale.square().mean(0).sqrt()
        return mu, sigma, aleatoric, members

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(self.in_keys[0])
        act = tensordict.get(self.in_keys[1])
        mu, sigma, aleatoric, _ = self.predict(obs, act)
        tensordict.set(self.out_keys[0], mu)
        tensordict.set(self.out_keys[1], sigma)
        tensordict.set(self.out_keys[2], aleatoric)
        return tensordict
