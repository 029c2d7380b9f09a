"""Probabilistic ensemble world model [mu_n, sigma_n] (paper: "Learning Uncertainty Aware Dynamics").

All L members live in stacked weight tensors of shape ``(L, in, out)`` and run in one
``torch.baddbmm`` per layer (training), or at inference by the measured fastest path (one grouped
convolution or batched matmul per layer, or the whole network in one call of our own kernels: bf16
in AMX tiles, :mod:`.amx_network`; fp32, or bf16 on AVX512-BF16, in register blocks,
:mod:`.fma_network`): there is no Python loop over members anywhere on the forward path.

Each member ``l`` predicts the normalized state *delta* ``(s' - s - m) / v`` from the normalized
input ``(s, a)`` together with a bounded log-variance (PETS soft bounds). In original units

    member mean     m_l(s, a) = s + m + v * NN_l(s, a)                  (L, *B, d_s)
    mean            mu(s, a)  = 1/L sum_l m_l(s, a)                     [mu]
    epistemic std   sigma     = sqrt(1/(L-1) sum_l (m_l - mu)^2)        [sigma]
    aleatoric std   sqrt(1/L sum_l var_l(s, a))                         [the noise w_t]
"""
from __future__ import annotations

import math
import os
import weakref
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torch.nn import functional as F
from torch.optim.optimizer import register_optimizer_step_post_hook

from torchrl_softae.modules import moments_kernel as _moments_kernel
from torchrl_softae.modules import paths
from torchrl_softae.modules import silu_kernel as _silu_kernel
from torchrl_softae.modules.kernels import kernels_allowed
from torchrl_softae.modules.paths import INFERENCE_PATHS, WHOLE_NETWORK_KERNELS
from torchrl_softae.modules.precision import onednn_bf16_available, resolve_planning_dtype
from torchrl_softae.modules.rollouts import DeterministicRollout, SampledRollout, is_rollout_key

__all__ = ["DeterministicRollout", "EnsembleLinear", "Normalizer", "EnsembleWorldModel", "SampledRollout",
           "ensemble_std", "symlog", "symexp"]


def _conv_weight_packer():
    """oneDNN's weight pre-packing for :func:`torch.ops.mkldnn._convolution_pointwise` (what
    inductor uses for frozen convolutions), or ``None`` in builds without the two."""
    if not hasattr(torch.ops.mkldnn, "_convolution_pointwise"):
        return None
    try:
        return torch.ops.mkldnn._reorder_convolution_weight
    except (AttributeError, RuntimeError):
        return None


_PACK_CONV_WEIGHT = _conv_weight_packer()



def _onednn_runs(dtype: torch.dtype) -> bool:
    """Whether oneDNN's own convolution (fused post-ops, pre-packed weights) takes ``dtype`` here."""
    return dtype != torch.bfloat16 or onednn_bf16_available()


#: Live models whose inference caches an optimizer step must clear (see :func:`_after_optimizer_step`).
_LIVE_MODELS: weakref.WeakSet = weakref.WeakSet()
_STEP_HOOK = None


def _after_optimizer_step(optimizer, args, kwargs) -> None:
    """Clears the inference cache of every live model whose parameters ``optimizer`` holds.

    The cache is keyed by the parameters' version counters, and fused optimizers (``Adam``,
    ``AdamW``, ``SGD`` with ``fused=True``; measured on torch 2.13 CPU) update parameters in place
    without moving them: without this hook a model trained that way would keep planning with its
    weights from before training."""
    models = [m for m in list(_LIVE_MODELS) if m._inference_cache]
    if not models:
        return
    held = {id(p) for group in optimizer.param_groups for p in group["params"]}
    for model in models:
        if any(id(layer.weight) in held or id(layer.bias) in held for layer in model.layers):
            model.clear_inference_cache()


def _watch_optimizer_steps(model) -> None:
    global _STEP_HOOK
    if _STEP_HOOK is None:
        _STEP_HOOK = register_optimizer_step_post_hook(_after_optimizer_step)
    _LIVE_MODELS.add(model)


#: distinct row counts per model whose convolution weights are packed exactly (see ``_pack_rows``)
_EXACT_PACKS = 8


def _row_bucket(rows: int) -> int:
    """The power of two at or above ``rows`` (at least 2): measured choices are kept per bucket, not
    per exact row count (packed weights too, once a model has seen ``_EXACT_PACKS`` counts)."""
    return 1 << max(int(rows) - 1, 1).bit_length()


def symlog(x: torch.Tensor) -> torch.Tensor:
    """``sign(x) log(1 + |x|)``: compresses large magnitudes, identity-like near 0 (DreamerV3)."""
    return torch.sign(x) * torch.log1p(x.abs())


def symexp(y: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`symlog`: ``sign(y) (exp(|y|) - 1)``."""
    return torch.sign(y) * torch.expm1(y.abs())


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
            works too). The CPU-only inference path (oneDNN grouped convolutions) is chosen per
            input device.

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
        uses_kernels = kernels_allowed(kernels)  # a bad choice is refused before anything is built
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
        #: whether this model may run compiled kernels (``kernels="auto"`` and not ``SOFTAE_KERNELS=0``)
        self.uses_kernels = uses_kernels
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
        # Reduced-precision planning: hidden 256x256 layers in this dtype (None = fp32).
        self.planning_dtype: torch.dtype | None = None
        self._inference_cache: dict = {}
        self._exact_pack_rows: set[int] = set()  # row counts whose conv weights are packed exactly
        self._path_memo: dict = {}  # measured choices (paths.choose) this model already looked up
        _watch_optimizer_steps(self)

    def __getstate__(self) -> dict:
        # a copy prepares its own rollouts: the prepared calls read the addresses of this model's
        # buffers (and cannot be pickled)
        state = super().__getstate__().copy()
        state["_inference_cache"] = {k: v for k, v in self._inference_cache.items() if not is_rollout_key(k)}
        return state

    def __setstate__(self, state) -> None:  # copies and unpickled models are watched too
        super().__setstate__(state)
        _watch_optimizer_steps(self)

    def _apply(self, fn, recurse=True):  # .to(), .double(), ...: new parameter storage
        self._inference_cache.clear()
        return super()._apply(fn, recurse)

    def clear_inference_cache(self) -> None:
        """Drops the cast and packed inference weights; they are rebuilt at the next call.

        Needed only after editing parameters through ``.data`` (invisible to their version
        counters); optimizer steps, fused or not, ``load_state_dict`` and ``.to()`` are detected."""
        self._inference_cache.clear()

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
                raise ValueError(
                    f"EnsembleWorldModel: {key!r} has shape {tuple(x.shape)}, expected (..., {d})"
                )
            self.check_dtype(key, x)
            if not torch.isfinite(x).all():
                bad = (~torch.isfinite(x)).nonzero()[0].tolist()
                raise ValueError(f"EnsembleWorldModel: {key!r} contains NaN/inf (first at index {bad})")
        if observation.shape[:-1] != action.shape[:-1]:
            raise ValueError(
                f"EnsembleWorldModel: batch shapes differ: {self.in_keys[0]!r} {tuple(observation.shape)} "
                f"vs {self.in_keys[1]!r} {tuple(action.shape)}"
            )

    # ------------------------------------------------------------------ raw network
    def _row_split(self, n_rows: int) -> int:
        """Chunks per member so the batched matmul's batch divides the thread count.

        ``bmm`` parallelizes over its batch: 5 members on 2 threads leave one thread idle a sixth
        of the time (measured: 20% slower than per-member GEMMs). Splitting each member's rows in
        ``k`` chunks makes the batch ``L * k`` a multiple of the threads.
        """
        threads = torch.get_num_threads()
        if threads <= 1 or self.ensemble_size % threads == 0:
            return 1
        k = threads // math.gcd(threads, self.ensemble_size)
        return k if n_rows % k == 0 and n_rows >= 8 * k else 1

    def _cached(self, layer: EnsembleLinear, key: tuple, build):
        """``build(weight, bias) -> (w, b)`` for ``layer``, cached until the parameters change: their
        version counter moves at every in-place update (a non-fused optimizer step,
        ``load_state_dict``); fused optimizer steps (:func:`_after_optimizer_step`) and ``.to()``
        (:meth:`_apply`) clear the cache."""
        key = (id(layer), *key)
        version = (layer.weight._version, layer.bias._version)
        hit = self._inference_cache.get(key)
        if hit is None or hit[0] != version:
            hit = self._inference_cache[key] = (version, *build(layer.weight.detach(), layer.bias.detach()))
        return hit[1], hit[2]

    def _inference_weights(self, layer: EnsembleLinear, dtype: torch.dtype, k: int, cols: int | None):
        """``layer``'s weights cast to ``dtype``, first ``cols`` outputs (all if ``None``), repeated
        ``k`` times per member."""

        def build(w, b):
            if cols is not None:
                w, b = w[..., :cols], b[..., :cols]
            return (w.repeat_interleave(k, dim=0).to(dtype).contiguous(),
                    b.repeat_interleave(k, dim=0).to(dtype).contiguous())

        return self._cached(layer, ("batched", dtype, k, cols), build)

    def _stacked_first_layer(self, dtype: torch.dtype):
        """First-layer weights of all members side by side, ``(in, L * h)`` and ``(L * h,)``."""
        layer = self.layers[0]
        return self._cached(layer, ("stacked", dtype), lambda w, b: (
            w.permute(1, 0, 2).reshape(layer.in_features, -1).to(dtype).contiguous(), b.reshape(-1).to(dtype)))

    def network(
        self, x: torch.Tensor, with_logvar: bool = True, bound_logvar: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Raw ensemble on normalized inputs.

        Args:
            x: ``(N, d_s + d_a)`` shared by all members, or ``(L, N, d_s + d_a)`` one batch per member.
            with_logvar: compute the log-variance head; planning with deterministic propagation
                does not need it and skips half of the output layer.
            bound_logvar: apply the soft bounds (``False``: raw head output, to bound only the
                entries actually used).

        Returns:
            normalized delta mean ``(L, N, d_s)`` and bounded normalized log-variance (same shape;
            ``None`` if not probabilistic or not requested).
        """
        d = self.observation_dim
        y = self.network_output(x, with_logvar).float()
        if not (self.probabilistic and with_logvar):
            return y[..., :d], None
        return y[..., :d], (self._bound_logvar(y[..., d:]) if bound_logvar else y[..., d:])

    def network_output(self, x: torch.Tensor, with_logvar: bool = True) -> torch.Tensor:
        """Raw ensemble on normalized inputs: the last layer's output ``(L, N, C)`` as the
        inference path leaves it (in the planning dtype, possibly a strided view of the layer's
        buffer; fp32 from the whole-network kernels, which do not round their last layer). Columns
        ``[:d_s]`` are the normalized delta means, ``[d_s:]`` the raw log-variances (when
        probabilistic and ``with_logvar``). Every prediction goes through here:
        :meth:`network`, :meth:`predict_members` and :meth:`predict_moments`."""
        d = self.observation_dim
        if torch.is_grad_enabled():  # training: plain autograd-friendly layers
            *hidden, last = self.layers  # (unpacked: slicing a ModuleList builds a new module)
            for layer in hidden:
                x = self.activation(layer(x))
            # The output head (mean and log-variance) stays in the weights' dtype under autocast:
            # in bf16 its rounding cost validation NLL on the arm (benchmarks/training_precision.py).
            with torch.autocast(x.device.type, enabled=False):
                return last(x.to(last.weight.dtype))
        lowp = self.planning_dtype or torch.float32
        cols = None if (with_logvar or not self.probabilistic) else d  # both heads in one matmul
        path = self._inference_path(x, lowp, cols) if x.dim() == 2 else "bmm"
        return self._run_path(path, x, lowp, cols)

    #: ``"auto"`` (measured once per device, dtype and row count; see :mod:`torchrl_softae.modules.paths`)
    #: or one of :data:`~torchrl_softae.modules.paths.INFERENCE_PATHS`; the environment variable
    #: ``SOFTAE_INFERENCE_PATH`` sets the default
    inference_path: str = "auto"

    def available_inference_paths(self, dtype: torch.dtype | None = None) -> tuple[str, ...]:
        """The inference paths this model can run here: the compiled-SiLU ones need ``nn.SiLU`` and
        the kernel built (:mod:`.silu_kernel`), the whole-network ones ``nn.SiLU`` and a CPU that
        runs their kernel (:mod:`.amx_network`, :mod:`.fma_network`). With ``dtype`` (the hidden
        layers' dtype), only those that run in it: ``conv-fused`` also needs an activation oneDNN
        fuses and oneDNN's own convolution in ``dtype`` (bf16 needs AVX512-BW/VL/DQ or
        AVX-NE-CONVERT); ``amx-network`` is bf16 only, ``fma-network`` fp32, or bf16 where the CPU has
        AVX512-BF16."""
        silu = type(self.activation) is nn.SiLU
        usable = tuple(p for p in INFERENCE_PATHS
                       if (not p.endswith("-silu-kernel") or self._silu_kernel_applies())
                       and (p not in WHOLE_NETWORK_KERNELS
                            or (self.uses_kernels and silu and WHOLE_NETWORK_KERNELS[p].available())))
        if dtype is None:
            return usable
        return tuple(p for p in usable
                     if (p != "conv-fused" or (self._fused_activation() is not None and _onednn_runs(dtype)))
                     and (p not in WHOLE_NETWORK_KERNELS or WHOLE_NETWORK_KERNELS[p].available(dtype)))

    def _inference_path(self, x: torch.Tensor, dtype: torch.dtype, cols: int | None) -> str:
        """Grouped convolutions (oneDNN, CPU only), batched matmuls or the AMX kernel for a shared
        ``(N, in)`` input: measured once per dtype, row bucket, head and thread count."""
        if x.device.type != "cpu" or not (torch.backends.mkldnn.is_available() and torch.backends.mkldnn.enabled):
            return "bmm"
        forced = self.inference_path if self.inference_path != "auto" else os.environ.get("SOFTAE_INFERENCE_PATH", "auto")
        if forced in INFERENCE_PATHS:
            if forced in WHOLE_NETWORK_KERNELS and forced not in self.available_inference_paths(dtype):
                kernel = WHOLE_NETWORK_KERNELS[forced]
                raise RuntimeError(f"inference path {forced!r} runs {kernel.RUNS}: got {dtype}, activation "
                                   f"{type(self.activation).__name__}, {kernel.why_not(dtype) or 'it runs here'}")
            if forced not in self.available_inference_paths():
                raise RuntimeError(f"inference path {forced!r} needs nn.SiLU and the compiled kernel "
                                   f"(activation {type(self.activation).__name__}, kernel built: {_silu_kernel.available()}, kernels allowed: {self.uses_kernels})")
            if forced == "conv-fused" and not _onednn_runs(dtype):
                raise RuntimeError(f"inference path 'conv-fused' in {dtype} needs oneDNN's bf16 convolution, which "
                                   "this CPU lacks (AVX512-BW/VL/DQ or AVX-NE-CONVERT); expected another path or fp32")
            return forced
        rows = _row_bucket(x.shape[0])
        memo = (dtype, rows, cols, torch.get_num_threads())
        if memo in self._path_memo:  # the hot path: no key string, no probe tensor per forward
            return self._path_memo[memo]
        shapes = ",".join(f"{layer.in_features}x{layer.out_features}" for layer in self.layers)
        # packed conv weights change how fast the conv paths are: a choice measured without them
        # (an older cache) is not this choice
        packing = "packed conv weights" if self._packs_conv_weights(dtype) else "plain conv weights"
        key = f"ensemble {self.ensemble_size}|{shapes}|{dtype}|rows {rows}|cols {cols}|{packing}"
        probe = torch.randn(rows, x.shape[1], dtype=x.dtype, generator=torch.Generator().manual_seed(0))
        candidates = {p: (lambda p=p: self._run_path(p, probe, dtype, cols))
                      for p in self.available_inference_paths(dtype)}
        self._path_memo[memo] = paths.choose(key, candidates)
        return self._path_memo[memo]

    def _run_path(self, path: str, x: torch.Tensor, dtype: torch.dtype, cols: int | None) -> torch.Tensor:
        """The network on a shared ``(N, in)`` input (or ``bmm`` on ``(L, N, in)``) by inference ``path``."""
        silu_kernel = path.endswith("-silu-kernel")
        if path in WHOLE_NETWORK_KERNELS:
            return self._network_whole(path, x, dtype, cols)
        if path.startswith("conv"):
            return self._network_grouped_conv(x, dtype, cols, fused=path == "conv-fused", silu_kernel=silu_kernel)
        return self._network_bmm(x, dtype, cols, silu_kernel=silu_kernel)

    @torch.no_grad()
    def auto_planning_dtype(self, rows: int = 2048) -> torch.dtype | None:
        """``precision="auto"``: bf16 where this device has native bf16 *and* the ensemble's
        inference measures faster in it (once per process and machine), else ``None`` (fp32)."""
        device = self.input_normalizer.loc.device
        if resolve_planning_dtype("auto", device) is None:
            return None
        rows = _row_bucket(rows)
        memo = ("precision", device.type, rows, torch.get_num_threads())
        if memo in self._path_memo:  # once per plan call: no probe tensor after the first
            return self._path_memo[memo]
        probe = torch.randn(rows, self.observation_dim + self.action_dim, device=device,
                            generator=torch.Generator(device=device).manual_seed(0))
        prev = self.planning_dtype

        def run(dtype):
            def fn():
                self.planning_dtype = dtype
                try:
                    self.network(probe, with_logvar=False)
                finally:
                    self.planning_dtype = prev
            return fn

        shapes = ",".join(f"{layer.in_features}x{layer.out_features}" for layer in self.layers)
        key = f"precision|{device.type}|ensemble {self.ensemble_size}|{shapes}|rows {rows}"
        choice = paths.choose(key, {"fp32": run(None), "bf16": run(torch.bfloat16)})
        self._path_memo[memo] = torch.bfloat16 if choice == "bf16" else None
        return self._path_memo[memo]

    def _network_grouped_conv(self, x: torch.Tensor, dtype: torch.dtype, cols: int | None,
                              fused: bool = False, silu_kernel: bool = False) -> torch.Tensor:
        """Inference on a shared ``(N, in)`` input: the ensemble as grouped 1x1 convolutions.

        The ``N`` rows are the pixels of a channels-last ``(1, C, N, 1)`` image whose channels are
        the ``L`` members' features side by side, so layer ``l`` of all members is ONE oneDNN
        convolution with ``groups=L`` (block-diagonal weights, no member loop) and activations stay
        in one ``(N, L * h)`` buffer from layer to layer (no transposes). Why not only ``baddbmm``:
        MKL, torch's fp32 GEMM on x86, takes an AVX2 path on AMD CPUs, where oneDNN's convolution
        is the faster fp32 GEMM (``benchmarks/planning_speed.py`` prints both).

        ``fused``: the hidden activation runs inside the convolution (a oneDNN post-op,
        :meth:`_fused_activation`): the layer's output is written once, already activated; in bf16
        the separate activation pass cost a third of a plan on a CPU with AMX.
        ``silu_kernel``: the separate activation pass by the compiled SiLU (:mod:`.silu_kernel`).

        Returns the ``(L, N, out)`` output in ``dtype`` as a view of an ``(N, L, out)`` buffer.
        """
        L, n = self.ensemble_size, x.shape[0]
        h = x.to(dtype).t().unsqueeze(0).unsqueeze(-1)  # (1, in, N, 1), channels-last view of x
        last = len(self.layers) - 1
        attr = self._fused_activation() if fused else None
        packed = self._packs_conv_weights(dtype)
        for i, layer in enumerate(self.layers):
            groups = 1 if i == 0 else L
            w, b = self._conv_weights(layer, dtype, cols if i == last else None, groups, n if packed else None)
            fuse = attr if i < last and attr is not None else None
            if packed or fuse is not None:
                h = torch.ops.mkldnn._convolution_pointwise(
                    h, w, b, [0, 0], [1, 1], [1, 1], groups, fuse or "none", [], "")
            else:
                h = F.conv2d(h, w, b, groups=groups)
            if i < last and fuse is None:
                h = self._activate_(h, silu_kernel)
        # (1, L * out, N, 1) channels-last is an (N, L * out) buffer: view it as (L, N, out)
        return h.squeeze(0).squeeze(-1).t().reshape(n, L, -1).transpose(0, 1)

    @staticmethod
    def _packs_conv_weights(dtype: torch.dtype) -> bool:
        """Whether the conv paths pre-pack their weights in ``dtype`` (where oneDNN takes it)."""
        return _PACK_CONV_WEIGHT is not None and _onednn_runs(dtype)

    def _pack_rows(self, rows: int) -> int:
        """The row count to pack convolution weights for: ``rows`` itself for the first
        :data:`_EXACT_PACKS` distinct counts (planning uses a handful), its bucket after them."""
        seen = self._exact_pack_rows
        if rows in seen or len(seen) < _EXACT_PACKS:
            seen.add(rows)
            return rows
        return _row_bucket(rows)

    def _conv_weights(self, layer: EnsembleLinear, dtype: torch.dtype, cols: int | None, groups: int,
                      rows: int | None = None):
        """``layer`` as a grouped 1x1 convolution: weight ``(L * out, in, 1, 1)`` in channels-last
        (oneDNN's fast path needs the weight in the input's memory format) and bias ``(L * out,)``.
        The first layer's members share the input: the same weight with ``groups=1``.

        ``rows``: also pack the weight into oneDNN's own blocked layout for inputs of that many rows,
        once, instead of oneDNN reordering the plain weight at every call (a large part of a bf16
        layer at planning's row counts). The pack is for the exact row count (the first
        :data:`_EXACT_PACKS` counts a model sees; a power-of-two bucket after them, so varying
        batch sizes cannot grow the cache without bound): a weight packed for more rows slows a
        convolution of fewer. Any row count is still correct with any pack (the same results as the
        plain weight: ``test_packed_conv_weights_match``)."""
        bucket = None if rows is None else self._pack_rows(rows)

        def build(w, b):
            if cols is not None:
                w, b = w[..., :cols], b[..., :cols]
            L, i, o = w.shape
            w = w.transpose(1, 2).reshape(L * o, i, 1, 1).to(dtype).contiguous().to(memory_format=torch.channels_last)
            if bucket is not None:
                w = _PACK_CONV_WEIGHT(w, [0, 0], [1, 1], [1, 1], groups, [1, i * groups, bucket, 1])
            return w, b.reshape(L * o).to(dtype).contiguous()

        return self._cached(layer, ("conv", dtype, cols, bucket), build)

    def _network_whole(self, path: str, x: torch.Tensor, dtype: torch.dtype, cols: int | None) -> torch.Tensor:
        """Inference on a shared ``(N, in)`` input in one call of a whole-network kernel
        (:data:`WHOLE_NETWORK_KERNELS`) in ``dtype``: every member's rows through all layers, the
        SiLU fused into each hidden layer; ``amx-network`` in bf16 AMX tiles, ``fma-network`` in
        fp32 or bf16 register blocks, fp32 accumulation. Returns ``(L, N, cols or out)`` in fp32
        (the last layer is not rounded)."""
        kernel = WHOLE_NETWORK_KERNELS[path]
        return kernel.forward(x.float(), self._packed_network(path, dtype, cols), cols or self.layers[-1].out_features)

    def _packed_network(self, path: str, dtype: torch.dtype, cols: int | None):
        """All layers packed for ``path``'s kernel in ``dtype`` (the last one's first ``cols``
        outputs), cached until a parameter changes (as :meth:`_cached`: its version counter moves;
        ``.to()`` and fused optimizer steps clear the cache). One check of the version counters of
        the parameters the entry holds per call, not a walk through the modules (a visible part of a
        small network call)."""
        key = ("whole network", path, dtype, cols)
        hit = self._inference_cache.get(key)
        if hit is not None and all(p._version == v for p, v in hit[0]):
            return hit[1]
        params = [p for layer in self.layers for p in (layer.weight, layer.bias)]
        layers = [(layer.weight.detach(), layer.bias.detach()) for layer in self.layers]
        if cols is not None:
            w, b = layers[-1]
            layers[-1] = (w[..., :cols], b[..., :cols])
        packed = WHOLE_NETWORK_KERNELS[path].pack_network(layers, dtype)
        self._inference_cache[key] = ([(p, p._version) for p in params], packed)
        return packed

    def _kernel_bias(self, layer: EnsembleLinear, k: int) -> torch.Tensor:
        """``layer``'s bias for :func:`~.silu_kernel.bias_silu_`, fp32 (the kernel adds it before
        the activation, in fp32 whatever the layer's dtype): ``(L * k, out)``, each member's row
        repeated ``k`` times as :meth:`_inference_weights` repeats its weights."""
        return self._cached(layer, ("kernel bias", k), lambda w, b: (
            None, b.reshape(layer.ensemble_size, -1).repeat_interleave(k, dim=0).float().contiguous()))[1]

    def _network_bmm(self, x: torch.Tensor, dtype: torch.dtype, cols: int | None,
                     silu_kernel: bool = False) -> torch.Tensor:
        """Inference with batched matmuls: ``x`` ``(N, in)`` shared or ``(L, N, in)`` per member.

        ``silu_kernel``: each hidden layer is a matmul without its bias and one pass of the
        compiled kernel that adds the bias and activates (:func:`~.silu_kernel.bias_silu_`);
        ``baddbmm`` would first copy the broadcast bias into its output, then read it back in the
        GEMM.
        """
        L = self.ensemble_size
        # a list, not a slice of the ModuleList: slicing builds a new ModuleList at every call
        *hidden, last = self.layers
        if x.dim() == 2:
            # shared input: the first layer of all members is ONE (N, in) x (in, L*h) GEMM
            # (a batched matmul with a small inner dimension is much slower)
            n = x.shape[0]
            w, b = self._stacked_first_layer(dtype)
            if silu_kernel:  # (L, 1, h) -> one row of L * h: every row of the (N, L * h) output
                h = _silu_kernel.bias_silu_(torch.mm(x.to(dtype), w), self._kernel_bias(hidden[0], 1).view(-1))
            else:
                h = self._activate_(torch.addmm(b, x.to(dtype), w))
            x = h.view(n, L, -1).transpose(0, 1).contiguous()
            hidden = hidden[1:]
        n = x.shape[1]
        # (bf16 bmm kernels are not batch-parallel in the same way: splitting does not pay)
        k = self._row_split(n) if dtype == torch.float32 else 1
        x = x.reshape(L * k, n // k, x.shape[-1])
        for layer in hidden:
            w, b = self._inference_weights(layer, dtype, k, None)
            if silu_kernel:
                x = _silu_kernel.bias_silu_(torch.bmm(x.to(dtype), w), self._kernel_bias(layer, k))
            else:
                x = self._activate_(torch.baddbmm(b, x.to(dtype), w))
        # All layers in reduced precision when asked (matmuls accumulate in fp32; the outputs
        # round to bf16): test_bf16_ranking_matches_fp32 checks that sigma-driven returns keep
        # their ranking (Spearman >= 0.95) on a trained model.
        w, b = self._inference_weights(last, dtype, k, cols)
        return torch.baddbmm(b, x, w).reshape(L, n, -1)

    def _fused_activation(self) -> str | None:
        """oneDNN's post-op name of the hidden activation, or ``None`` where it has none (or this
        torch build lacks the fused convolution)."""
        if not hasattr(torch.ops.mkldnn, "_convolution_pointwise"):
            return None
        return {nn.SiLU: "swish", nn.ReLU: "relu", nn.Tanh: "tanh", nn.Hardswish: "hardswish",
                nn.Sigmoid: "sigmoid"}.get(type(self.activation))

    def _silu_kernel_applies(self) -> bool:
        return self.uses_kernels and type(self.activation) is nn.SiLU and _silu_kernel.available()

    def _activate_(self, x: torch.Tensor, silu_kernel: bool = False) -> torch.Tensor:
        """Activation in place on a fresh matmul output (inference only): a second large
        allocation per layer cost more than the bf16 SiLU itself (measured). ``silu_kernel``: by
        the compiled SiLU (only on a path that measured faster with it)."""
        if silu_kernel:
            return _silu_kernel.silu_(x)
        fn = {nn.SiLU: F.silu, nn.ReLU: F.relu, nn.ELU: F.elu, nn.Hardswish: F.hardswish}.get(type(self.activation))
        return fn(x, inplace=True) if fn is not None else self.activation(x)

    def _bound_logvar(self, logvar: torch.Tensor) -> torch.Tensor:
        """PETS soft bounds: smooth clamp of the log-variance into [min_logvar, max_logvar]."""
        hi, lo = self.max_logvar.to(logvar.dtype), self.min_logvar.to(logvar.dtype)
        logvar = hi - F.softplus(hi - logvar)
        return lo + F.softplus(logvar - lo)

    def normalized_members(
        self, observation: torch.Tensor, action: torch.Tensor, with_logvar: bool = True, bound_logvar: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Normalized delta predictions for flat inputs.

        ``observation`` ``(N, d_s)`` and ``action`` ``(N, d_a)`` (shared by all members), or with a
        leading member dim ``(L, N, ...)`` (each member on its own minibatch, for training).
        """
        return self.network(self.network_input(observation, action), with_logvar, bound_logvar)

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
        member_index: torch.Tensor | None = None, *, action_normalized: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Every member's next-state mean and aleatoric std in original units.

        Args:
            observation: ``(*B, d_s)``; action: ``(*B, d_a)``.
            with_aleatoric: also compute the aleatoric std (else ``None`` is returned for it).
            member_index: ``(*B,)`` member per row (trajectory sampling): the aleatoric std is then
                computed for that member only and returned with shape ``(*B, d_s)``.
            action_normalized: ``action`` is :meth:`normalized_actions` of the actions.

        Returns:
            ``(L, *B, d_s)`` member means [NN_l(s, a)] and ``(L, *B, d_s)`` aleatoric stds.
        """
        batch = observation.shape[:-1]
        obs = observation.reshape(-1, self.observation_dim)
        act = action.reshape(-1, self.action_dim)
        raw = self.network_output(self.network_input(obs, act, action_normalized), with_aleatoric)
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

    #: compute mu and sigma (and a sampled member's mean) in one pass over the network output with
    #: the compiled kernel (:mod:`.moments_kernel`) where it applies; ``False``: torch ops (to compare)
    fused_moments: bool = True

    def predict_moments(
        self, observation: torch.Tensor, action: torch.Tensor, with_aleatoric: bool = False,
        member_index: torch.Tensor | None = None, *, action_normalized: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """What propagation needs from the ensemble at ``(s, a)``, without the member means.

        Args:
            observation: ``(*B, d_s)``; action: ``(*B, d_a)``.
            with_aleatoric: also return the aleatoric std.
            member_index: ``(*B,)`` member per row (trajectory sampling), or ``None``.
            action_normalized: ``action`` is :meth:`normalized_actions` of the actions.

        Returns:
            ``mu`` [mu] and ``sigma`` [sigma] ``(*B, d_s)``; the mean of member ``member_index``
            ``(*B, d_s)`` (``None`` without it); the aleatoric std ``(*B, d_s)``: that member's, or
            without ``member_index`` the root mean square over the members (``None`` unless
            ``with_aleatoric``).

        At inference on a CPU with AVX2 or AVX-512 this is one pass over the network's output, in its
        dtype, where the member means are never materialized (``fused_moments``,
        :mod:`.moments_kernel`); elsewhere the torch ops of :meth:`predict_members`. Both give the
        same values to fp32 rounding (``test_fused_moments_match_the_torch_ops``).
        """
        d = self.observation_dim
        batch = observation.shape[:-1]
        obs = observation.reshape(-1, d)
        act = action.reshape(-1, self.action_dim)
        if member_index is not None:
            member_index = member_index.reshape(-1)
        raw = self.network_output(self.network_input(obs, act, action_normalized), with_aleatoric)
        mu, sigma, member_mean, ale = self._moments_from_output(raw, obs, with_aleatoric, member_index)
        shape = (*batch, d)
        return (mu.reshape(shape), sigma.reshape(shape), None if member_mean is None else member_mean.reshape(shape),
                None if ale is None else ale.reshape(shape))

    def deterministic_rollout(self, observation: torch.Tensor, normalized_actions: torch.Tensor,
                              eta: torch.Tensor | None = None) -> "DeterministicRollout":
        """The model steps of a deterministic planning rollout (Mean-AE: ``s' = mu``; SoftAE and
        H-UCRL: ``s' = mu + sigma * eta``), laid out once: see :class:`DeterministicRollout`.

        Args:
            observation: ``(M, d_s)`` the initial states of ``M`` candidates.
            normalized_actions: ``(H, M, d_a)`` their actions, step by step, as the network takes
                them (:meth:`normalized_actions`).
            eta: ``(H, M, d_s)`` the hallucinated control with beta applied, or ``None``.
        """
        return DeterministicRollout(self, observation, normalized_actions, eta)

    def sampled_rollout(self, observation: torch.Tensor, normalized_actions: torch.Tensor,
                        member_index: torch.Tensor, aleatoric_noise: bool = True,
                        generator: torch.Generator | None = None) -> "SampledRollout":
        """The model steps of a trajectory-sampling planning rollout (PETS-AE, TS-inf: each particle
        follows one member for the whole horizon, ``s' = m_l + std_l * z``), laid out once: see
        :class:`SampledRollout`.

        Args:
            observation: ``(M, d_s)`` the initial states of ``M`` candidates.
            normalized_actions: ``(H, M, d_a)`` their actions, step by step, as the network takes
                them (:meth:`normalized_actions`), shared by a candidate's particles.
            member_index: ``(M, P)`` int, the member each of a candidate's ``P`` particles follows.
            aleatoric_noise: draw the member's aleatoric noise (else ``s' = m_l``).
            generator: the noise's source, consumed as by one draw per step.
        """
        return SampledRollout(self, observation, normalized_actions, member_index, aleatoric_noise, generator)

    def _moments_from_output(self, raw, obs, with_aleatoric=False, member_index=None, eta=None, next_input=None):
        """:meth:`predict_moments` (and a deterministic rollout's ``eta`` and ``next_input``) from the
        raw network output ``raw`` ``(L, N, C)`` at the flat states ``obs`` ``(N, d_s)``; flat
        ``(N, d_s)`` results."""
        d = self.observation_dim
        fused = (self.fused_moments and self.uses_kernels and not self.symlog_observations and _moments_kernel.applies(raw)
                 and (member_index is not None or not with_aleatoric))
        norm = self.input_normalizer
        if fused:
            with_logvar = with_aleatoric and self.probabilistic
            out = self.output_normalizer
            # the bounds and the aleatoric std in the same pass, where the bounds' span allows it
            bounds = self._fused_logvar_bounds() if with_logvar else None
            next_state = {} if next_input is None else dict(
                next_input=next_input, input_loc=norm.loc[:d], input_scale=norm.scale[:d])
            mu, sigma, member_mean, second = _moments_kernel.ensemble_moments(
                raw, obs, out.loc, out.scale, d, member_index, with_logvar, bounds, eta=eta, **next_state)
            ale = None
            if with_aleatoric:
                if not with_logvar:
                    ale = torch.zeros_like(mu)
                else:  # the raw log-variance where the kernel did not bound it
                    ale = second if bounds is not None else self._aleatoric_std(self._bound_logvar(second))
            return mu, sigma, member_mean, ale
        members, ale = self._members_from_output(raw, obs, (obs.shape[0],), with_aleatoric, member_index)
        mu = members.mean(0)
        sigma = ensemble_std(members, mu)
        member_mean = None
        if member_index is not None:
            member_mean = members.gather(0, member_index.reshape(1, -1, 1).expand(1, *mu.shape)).squeeze(0)
        elif ale is not None:
            ale = ale.square().mean(0).sqrt()
        if eta is not None:
            mu = torch.addcmul(mu, sigma, eta)
        if next_input is not None:
            next_input[:, :d] = self._normalized_states(mu)
        return mu, sigma, member_mean, ale

    def _fused_logvar_bounds(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The log-variance bounds ``(min_logvar, max_logvar)`` where the moments kernel can apply
        them and form the aleatoric std in its pass (a span below
        :data:`~.moments_kernel.MAX_LOGVAR_SPAN`), else ``None``."""
        if bool((self.max_logvar - self.min_logvar).max() < _moments_kernel.MAX_LOGVAR_SPAN):
            return self.min_logvar, self.max_logvar
        return None

    def predict(
        self, observation: torch.Tensor, action: torch.Tensor, check: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Returns ``(mu, sigma, aleatoric_std, members)``; shapes ``(*B, d_s)`` and ``(L, *B, d_s)``."""
        if check:
            self._check(observation, action)
        members, ale = self.predict_members(observation, action)
        mu = members.mean(0)
        sigma = ensemble_std(members, mu)
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
