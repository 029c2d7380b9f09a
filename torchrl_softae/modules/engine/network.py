"""The ensemble's inference engine: everything :class:`~torchrl_softae.modules.EnsembleWorldModel`
runs at inference for speed, apart from the model's maths.

- The network by the measured fastest path (:mod:`.paths`): one grouped oneDNN convolution or
  batched matmul per layer, or the whole network in one call of our kernels (bf16 in AMX tiles,
  :mod:`.amx_network`; fp32, or bf16 on AVX512-BF16, in register blocks, :mod:`.fma_network`), with
  the weights cast, packed and cached until a parameter changes.
- mu and sigma in one pass over the network's output (:mod:`.moments_kernel`), the fast twin of the
  model's torch formulas.
- Planning rollouts laid out once (:mod:`.rollouts`).

:mod:`torchrl_softae.modules` attaches an :class:`InferenceEngine` to every model it builds
(``model.engine``); the model never imports this package. ``kernels="torch"`` (or
``SOFTAE_KERNELS=0``) keeps the engine to torch's own ops.
"""
from __future__ import annotations

import math
import weakref

import torch
from torch import nn
from torch.nn import functional as F
from torch.optim.optimizer import register_optimizer_step_post_hook

from torchrl_softae.modules.engine import moments_kernel as _moments_kernel
from torchrl_softae.modules.engine import paths
from torchrl_softae.modules.engine import silu_kernel as _silu_kernel
from torchrl_softae.modules.engine.kernels import kernels_allowed
from torchrl_softae.modules.engine.paths import INFERENCE_PATHS, WHOLE_NETWORK_KERNELS
from torchrl_softae.modules.engine.precision import onednn_bf16_available, resolve_planning_dtype
from torchrl_softae.modules.engine.rollouts import DeterministicRollout, SampledRollout, is_rollout_key

__all__ = ["InferenceEngine"]


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


#: Live engines whose inference caches an optimizer step must clear (see :func:`_after_optimizer_step`).
_LIVE_ENGINES: weakref.WeakSet = weakref.WeakSet()
_STEP_HOOK = None


def _after_optimizer_step(optimizer, args, kwargs) -> None:
    """Clears the inference cache of every live engine whose model's parameters ``optimizer`` holds.

    The cache is keyed by the parameters' version counters, and fused optimizers (``Adam``,
    ``AdamW``, ``SGD`` with ``fused=True``; measured on torch 2.13 CPU) update parameters in place
    without moving them: without this hook a model trained that way would keep planning with its
    weights from before training."""
    engines = [e for e in list(_LIVE_ENGINES) if e._inference_cache]
    if not engines:
        return
    held = {id(p) for group in optimizer.param_groups for p in group["params"]}
    for engine in engines:
        if any(id(layer.weight) in held or id(layer.bias) in held for layer in engine.model.layers):
            engine.clear_inference_cache()


def _watch_optimizer_steps(engine) -> None:
    global _STEP_HOOK
    if _STEP_HOOK is None:
        _STEP_HOOK = register_optimizer_step_post_hook(_after_optimizer_step)
    _LIVE_ENGINES.add(engine)


#: distinct row counts per model whose convolution weights are packed exactly (see ``_pack_rows``)
_EXACT_PACKS = 8


def _row_bucket(rows: int) -> int:
    """The power of two at or above ``rows`` (at least 2): measured choices are kept per bucket, not
    per exact row count (packed weights too, once a model has seen ``_EXACT_PACKS`` counts)."""
    return 1 << max(int(rows) - 1, 1).bit_length()


class InferenceEngine:
    """The inference of one :class:`~torchrl_softae.modules.EnsembleWorldModel` (``model.engine``).

    Args:
        model: the ensemble it runs.
        kernels: ``"auto"`` runs a compiled kernel where it is built, applies and measured faster;
            ``"torch"`` never does (nor does any engine under ``SOFTAE_KERNELS=0``).

    The model's one switch is ``kernels=`` (and ``SOFTAE_KERNELS=0`` for the whole process); the
    attributes below pick one contender at a time, for the benchmarks and tests that compare them.
    The hidden layers' dtype (bf16 planning) is an argument of each call, never state.

    Attributes:
        inference_path: ``"auto"`` (measured once per device, dtype and row count, :mod:`.paths`) or
            one of :data:`~.paths.INFERENCE_PATHS`.
        fused_moments: mu and sigma (and a sampled member's mean) by the moments kernel where it
            applies; ``False``: by the model's torch formulas.
        rollouts: a model env scores deterministic and trajectory-sampling plans through
            :meth:`deterministic_rollout` / :meth:`sampled_rollout`; ``False``: step by step.
        kernel_noise: aleatoric noise by the counter-based normal kernel where it applies;
            ``False``: ``torch.randn``.
    """

    inference_path: str = "auto"
    fused_moments: bool = True
    rollouts: bool = True
    kernel_noise: bool = True

    def __init__(self, model, kernels: str = "auto"):
        self.model = model
        #: whether this engine may run compiled kernels (``kernels="auto"`` and not ``SOFTAE_KERNELS=0``)
        self.uses_kernels = kernels_allowed(kernels)
        self._inference_cache: dict = {}
        self._exact_pack_rows: set[int] = set()  # row counts whose conv weights are packed exactly
        self._path_memo: dict = {}  # measured choices (paths.choose) this engine already looked up
        _watch_optimizer_steps(self)

    def __getstate__(self) -> dict:
        # a copy prepares its own rollouts: the prepared calls read the addresses of this model's
        # buffers (and cannot be pickled)
        state = self.__dict__.copy()
        state["_inference_cache"] = {k: v for k, v in self._inference_cache.items() if not is_rollout_key(k)}
        return state

    def __setstate__(self, state) -> None:  # copies and unpickled models are watched too
        self.__dict__.update(state)
        _watch_optimizer_steps(self)

    def clear_inference_cache(self) -> None:
        """Drops the cast and packed inference weights; they are rebuilt at the next call.

        Needed only after editing parameters through ``.data`` (invisible to their version
        counters); optimizer steps, fused or not, ``load_state_dict`` and ``.to()`` are detected."""
        self._inference_cache.clear()

    def network_output(self, x: torch.Tensor, with_logvar: bool = True, dtype: torch.dtype | None = None) -> torch.Tensor:
        """:meth:`EnsembleWorldModel.network_output` at inference: the last layer's output
        ``(L, N, C)`` as the inference path leaves it (in the planning dtype, possibly a strided view
        of the layer's buffer; fp32 from the whole-network kernels, which do not round their last
        layer); without ``with_logvar`` only the mean head's ``d_s`` columns; the hidden layers in
        ``dtype`` (``None``: fp32)."""
        lowp = dtype or torch.float32
        model = self.model
        cols = None if (with_logvar or not model.probabilistic) else model.observation_dim
        path = self._inference_path(x, lowp, cols) if x.dim() == 2 else "bmm"
        return self._run_path(path, x, lowp, cols)

    def _row_split(self, n_rows: int) -> int:
        """Chunks per member so the batched matmul's batch divides the thread count.

        ``bmm`` parallelizes over its batch: 5 members on 2 threads leave one thread idle a sixth
        of the time (measured: 20% slower than per-member GEMMs). Splitting each member's rows in
        ``k`` chunks makes the batch ``L * k`` a multiple of the threads.
        """
        threads = torch.get_num_threads()
        if threads <= 1 or self.model.ensemble_size % threads == 0:
            return 1
        k = threads // math.gcd(threads, self.model.ensemble_size)
        return k if n_rows % k == 0 and n_rows >= 8 * k else 1

    def _cached(self, layer, key: tuple, build):
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

    def _inference_weights(self, layer, dtype: torch.dtype, k: int, cols: int | None):
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
        layer = self.model.layers[0]
        return self._cached(layer, ("stacked", dtype), lambda w, b: (
            w.permute(1, 0, 2).reshape(layer.in_features, -1).to(dtype).contiguous(), b.reshape(-1).to(dtype)))

    def available_inference_paths(self, dtype: torch.dtype | None = None) -> tuple[str, ...]:
        """The inference paths this model can run here: the compiled-SiLU ones need ``nn.SiLU`` and
        the kernel built (:mod:`.silu_kernel`), the whole-network ones ``nn.SiLU`` and a CPU that
        runs their kernel (:mod:`.amx_network`, :mod:`.fma_network`). With ``dtype`` (the hidden
        layers' dtype), only those that run in it: ``conv-fused`` also needs an activation oneDNN
        fuses and oneDNN's own convolution in ``dtype`` (bf16 needs AVX512-BW/VL/DQ or
        AVX-NE-CONVERT); ``amx-network`` is bf16 only, ``fma-network`` fp32, or bf16 where the CPU has
        AVX512-BF16."""
        silu = type(self.model.activation) is nn.SiLU
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
        forced = self.inference_path
        if forced in INFERENCE_PATHS:
            if forced in WHOLE_NETWORK_KERNELS and forced not in self.available_inference_paths(dtype):
                kernel = WHOLE_NETWORK_KERNELS[forced]
                raise RuntimeError(f"inference path {forced!r} runs {kernel.RUNS}: got {dtype}, activation "
                                   f"{type(self.model.activation).__name__}, {kernel.why_not(dtype) or 'it runs here'}")
            if forced not in self.available_inference_paths():
                raise RuntimeError(f"inference path {forced!r} needs nn.SiLU and the compiled kernel "
                                   f"(activation {type(self.model.activation).__name__}, kernel built: {_silu_kernel.available()}, kernels allowed: {self.uses_kernels})")
            if forced == "conv-fused" and not _onednn_runs(dtype):
                raise RuntimeError(f"inference path 'conv-fused' in {dtype} needs oneDNN's bf16 convolution, which "
                                   "this CPU lacks (AVX512-BW/VL/DQ or AVX-NE-CONVERT); expected another path or fp32")
            return forced
        rows = _row_bucket(x.shape[0])
        memo = (dtype, rows, cols, torch.get_num_threads())
        if memo in self._path_memo:  # the hot path: no key string, no probe tensor per forward
            return self._path_memo[memo]
        shapes = ",".join(f"{layer.in_features}x{layer.out_features}" for layer in self.model.layers)
        # packed conv weights change how fast the conv paths are: a choice measured without them
        # (an older cache) is not this choice
        packing = "packed conv weights" if self._packs_conv_weights(dtype) else "plain conv weights"
        key = f"ensemble {self.model.ensemble_size}|{shapes}|{dtype}|rows {rows}|cols {cols}|{packing}"
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
        device = self.model.input_normalizer.loc.device
        if resolve_planning_dtype("auto", device) is None:
            return None
        rows = _row_bucket(rows)
        memo = ("precision", device.type, rows, torch.get_num_threads())
        if memo in self._path_memo:  # once per plan call: no probe tensor after the first
            return self._path_memo[memo]
        probe = torch.randn(rows, self.model.observation_dim + self.model.action_dim, device=device,
                            generator=torch.Generator(device=device).manual_seed(0))
        def run(dtype):
            return lambda: self.model.network_output(probe, with_logvar=False, dtype=dtype)

        shapes = ",".join(f"{layer.in_features}x{layer.out_features}" for layer in self.model.layers)
        key = f"precision|{device.type}|ensemble {self.model.ensemble_size}|{shapes}|rows {rows}"
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
        L, n = self.model.ensemble_size, x.shape[0]
        h = x.to(dtype).t().unsqueeze(0).unsqueeze(-1)  # (1, in, N, 1), channels-last view of x
        last = len(self.model.layers) - 1
        attr = self._fused_activation() if fused else None
        packed = self._packs_conv_weights(dtype)
        for i, layer in enumerate(self.model.layers):
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

    def _conv_weights(self, layer, dtype: torch.dtype, cols: int | None, groups: int,
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
        return kernel.forward(x.float(), self._packed_network(path, dtype, cols), cols or self.model.layers[-1].out_features)

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
        params = [p for layer in self.model.layers for p in (layer.weight, layer.bias)]
        layers = [(layer.weight.detach(), layer.bias.detach()) for layer in self.model.layers]
        if cols is not None:
            w, b = layers[-1]
            layers[-1] = (w[..., :cols], b[..., :cols])
        packed = WHOLE_NETWORK_KERNELS[path].pack_network(layers, dtype)
        self._inference_cache[key] = ([(p, p._version) for p in params], packed)
        return packed

    def _kernel_bias(self, layer, k: int) -> torch.Tensor:
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
        L = self.model.ensemble_size
        # a list, not a slice of the ModuleList: slicing builds a new ModuleList at every call
        *hidden, last = self.model.layers
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
                nn.Sigmoid: "sigmoid"}.get(type(self.model.activation))

    def _silu_kernel_applies(self) -> bool:
        return self.uses_kernels and type(self.model.activation) is nn.SiLU and _silu_kernel.available()

    def _activate_(self, x: torch.Tensor, silu_kernel: bool = False) -> torch.Tensor:
        """Activation in place on a fresh matmul output (inference only): a second large
        allocation per layer cost more than the bf16 SiLU itself (measured). ``silu_kernel``: by
        the compiled SiLU (only on a path that measured faster with it)."""
        if silu_kernel:
            return _silu_kernel.silu_(x)
        fn = {nn.SiLU: F.silu, nn.ReLU: F.relu, nn.ELU: F.elu, nn.Hardswish: F.hardswish}.get(type(self.model.activation))
        return fn(x, inplace=True) if fn is not None else self.model.activation(x)

    def moments(self, raw, obs, with_aleatoric=False, member_index=None, eta=None, next_input=None):
        """:meth:`EnsembleWorldModel.moments_from_output` in one pass of the moments kernel over
        ``raw`` (in its dtype; the member means are never materialized), or ``None`` where the
        kernel does not apply (then the model's torch formulas run). Both give the same values to
        fp32 rounding (``test_fused_moments_match_the_torch_ops``)."""
        model = self.model
        if not (self.fused_moments and self.uses_kernels and not model.symlog_observations
                and _moments_kernel.applies(raw) and (member_index is not None or not with_aleatoric)):
            return None
        d = model.observation_dim
        norm, out = model.input_normalizer, model.output_normalizer
        with_logvar = with_aleatoric and model.probabilistic
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
                ale = second if bounds is not None else model._aleatoric_std(model._bound_logvar(second))
        return mu, sigma, member_mean, ale

    def _fused_logvar_bounds(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The log-variance bounds ``(min_logvar, max_logvar)`` where the moments kernel can apply
        them and form the aleatoric std in its pass (a span below
        :data:`~.moments_kernel.MAX_LOGVAR_SPAN`), else ``None``."""
        if bool((self.model.max_logvar - self.model.min_logvar).max() < _moments_kernel.MAX_LOGVAR_SPAN):
            return self.model.min_logvar, self.model.max_logvar
        return None

    def deterministic_rollout(self, observation: torch.Tensor, normalized_actions: torch.Tensor,
                              eta: torch.Tensor | None = None, dtype: torch.dtype | None = None) -> "DeterministicRollout":
        """The model steps of a deterministic planning rollout (Mean-AE: ``s' = mu``; SoftAE and
        H-UCRL: ``s' = mu + sigma * eta``), laid out once: see :class:`DeterministicRollout`.

        Args:
            observation: ``(M, d_s)`` the initial states of ``M`` candidates.
            normalized_actions: ``(H, M, d_a)`` their actions, step by step, as the network takes
                them (:meth:`EnsembleWorldModel.normalized_actions`).
            eta: ``(H, M, d_s)`` the hallucinated control with beta applied, or ``None``.
            dtype: the hidden layers' dtype (``None``: fp32).
        """
        return DeterministicRollout(self.model, observation, normalized_actions, eta, dtype)

    def sampled_rollout(self, observation: torch.Tensor, normalized_actions: torch.Tensor,
                        member_index: torch.Tensor, aleatoric_noise: bool = True,
                        generator: torch.Generator | None = None, dtype: torch.dtype | None = None) -> "SampledRollout":
        """The model steps of a trajectory-sampling planning rollout (PETS-AE, TS-inf: each particle
        follows one member for the whole horizon, ``s' = m_l + std_l * z``), laid out once: see
        :class:`SampledRollout`.

        Args:
            observation: ``(M, d_s)`` the initial states of ``M`` candidates.
            normalized_actions: ``(H, M, d_a)`` their actions, step by step, as the network takes
                them (:meth:`EnsembleWorldModel.normalized_actions`), shared by a candidate's particles.
            member_index: ``(M, P)`` int, the member each of a candidate's ``P`` particles follows.
            aleatoric_noise: draw the member's aleatoric noise (else ``s' = m_l``).
            generator: the noise's source, consumed as by one draw per step.
            dtype: the hidden layers' dtype (``None``: fp32).
        """
        return SampledRollout(self.model, observation, normalized_actions, member_index, aleatoric_noise, generator,
                              dtype)
