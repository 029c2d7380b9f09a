"""The ensemble's whole network in one call of fused multiply-adds
(``torchrl_softae/modules/engine/csrc/fma_network.c``), fp32 or bf16.

Every member's block of up to 12 rows (AVX-512; 6 with AVX2) runs through all layers in register
blocks, each hidden layer's bias and SiLU applied in registers, the last layer written out in
fp32: one call per network call instead of five GEMM calls and four activation passes. fp32 runs
where the CPU has AVX-512F or AVX2 with FMA (:func:`isa`); bf16 (weights and hidden activations,
fp32 accumulation, VDPBF16PS) where it has AVX512-BF16. Built at install time where a C compiler
is present (an optional extension). The ensemble offers it as the inference path ``fma-network``
(SiLU; :func:`available` in the planning dtype) and takes it only where it measures faster
(:mod:`~torchrl_softae.modules.engine.paths`).
"""
from __future__ import annotations

import torch

from torchrl_softae.modules.engine._fused_network import PackedLayer, PackedNetworkBase, prepare, run
from torchrl_softae.modules.engine._instruction_sets import instruction_set_functions
from torchrl_softae.modules.engine.kernels import load_extension

_fma_network = load_extension("_fma_network")  # after torch (None: not built, or SOFTAE_KERNELS=0)

__all__ = ["RUNS", "available", "why_not", "isa", "supported_isas", "use_isa", "cache_tag", "pack_layer", "pack_network",
           "forward", "prepare_forward", "PackedLayer", "PackedNetwork", "DTYPES"]

#: output columns per packed weight panel (two AVX-512 registers, four AVX2 ones)
_PANEL = 32
#: the dtypes the kernel computes in
DTYPES = (torch.float32, torch.bfloat16)

#: the instruction set the fp32 kernel runs on (``"avx512f"`` or ``"avx2"``), the ones this CPU
#: runs it on, and a switch between them (for tests); bf16 runs on AVX512-BF16 only
isa, supported_isas, use_isa = instruction_set_functions(_fma_network)


def available(dtype: torch.dtype = torch.float32) -> bool:
    """Whether the extension was built and this CPU runs it in ``dtype``."""
    if _fma_network is None or isa() is None:
        return False
    return dtype == torch.float32 or (dtype == torch.bfloat16 and _fma_network.bf16_supported())


#: what the kernel runs, for errors that name it (as :data:`.amx_network.RUNS`)
RUNS = "fp32 (AVX-512F or AVX2+FMA) or bf16 (AVX512-BF16) with nn.SiLU"


def why_not(dtype: torch.dtype = torch.float32) -> str | None:
    """Why :func:`available` is ``False`` (``None`` where it is ``True``)."""
    if _fma_network is None:
        return "the extension torchrl_softae.modules.engine._fma_network was not built (no C compiler)"
    if isa() is None:
        return "the CPU has neither AVX-512F nor AVX2 with FMA"
    if dtype not in DTYPES:
        return f"it computes in float32 or bfloat16, not {dtype}"
    return None if available(dtype) else "the CPU has no AVX512-BF16 (the bf16 form)"


def cache_tag() -> str | None:
    """The kernel as cached measurements name it: its instruction sets and revision (``None``
    where it does not run)."""
    if not available():
        return None
    return f"{isa()}{'+avx512bf16' if available(torch.bfloat16) else ''} revision {_fma_network.REVISION}"


def pack_layer(weight: torch.Tensor, bias: torch.Tensor, inputs: int | None = None,
               dtype: torch.dtype = torch.float32) -> PackedLayer:
    """One ensemble layer in the kernel's layout.

    Args:
        weight: ``(L, K, M)`` (``x @ weight[l]`` is member ``l``'s layer), any float dtype.
        bias: ``(L, M)`` or ``(L, 1, M)``.
        inputs: the packed layer's inputs, ``K`` or more (zero rows beyond ``K``): a hidden
            layer takes the previous layer's padded outputs. Default ``K`` (fp32) or ``K``
            rounded up to even (bf16).
        dtype: ``torch.float32`` or ``torch.bfloat16``.

    Returns:
        the weight, fp32 ``(L, Mp / 32, inputs, 32)`` (panel ``p`` holding ``W[k, 32 p + j]``) or
        bf16 ``(L, Mp / 32, inputs / 2, 32, 2)`` (``[p, i, j, t]`` holding ``W[2 i + t, 32 p + j]``:
        pairs of inputs side by side), zeros where ``32 p + j >= M`` or ``k >= K``; and the bias
        ``(L, Mp)`` fp32; ``Mp``: ``M`` padded to a multiple of 32.
    """
    if dtype not in DTYPES:
        raise ValueError(f"fma_network.pack_layer: dtype={dtype}, expected one of {DTYPES}")
    members, k, m = weight.shape
    pairs = dtype == torch.bfloat16
    inputs = (k + k % 2 if pairs else k) if inputs is None else inputs
    if inputs < k or (pairs and inputs % 2):
        raise ValueError(f"fma_network.pack_layer: inputs={inputs}, expected at least the weight's {k}"
                         + (" and even (bf16 pairs)" if pairs else ""))
    mp = -(-m // _PANEL) * _PANEL
    w = torch.zeros(members, inputs, mp, dtype=dtype, device=weight.device)
    w[:, :k, :m] = weight
    if pairs:  # (L, i, t, p, j) -> (L, p, i, j, t)
        w = w.view(members, inputs // 2, 2, mp // _PANEL, _PANEL).permute(0, 3, 1, 4, 2).contiguous()
    else:
        w = w.view(members, inputs, mp // _PANEL, _PANEL).permute(0, 2, 1, 3).contiguous()
    b = torch.zeros(members, mp, dtype=torch.float32, device=weight.device)
    b[:, :m] = bias.reshape(members, m)
    return w, b


def pack_network(layers: list[tuple[torch.Tensor, torch.Tensor]], dtype: torch.dtype = torch.float32
                 ) -> "PackedNetwork":
    """A whole network, ``[(weight (L, K, M), bias), ...]`` first to last, packed in ``dtype``:
    each hidden layer takes the previous one's padded outputs, the first the input (fp32:
    unpadded; bf16: padded to an even count)."""
    packed: list[PackedLayer] = []
    for w, b in layers:
        packed.append(pack_layer(w, b, None if not packed else PackedNetwork._out_features(packed[-1][0]), dtype))
    return PackedNetwork(packed, layers[0][0].shape[1])


class PackedNetwork(PackedNetworkBase):
    """Every layer of an ensemble network in the kernel's layout (:func:`pack_layer`), checked
    once, with the kernel's arguments prepared (:class:`~._fused_network.PackedNetworkBase`).
    In fp32 ``in_features`` must equal the first layer's ``K`` (the kernel reads the input
    unpadded); in bf16 it may be one less (the kernel pads the input to pairs)."""

    kernel = "fma_network"

    @staticmethod
    def _layer_error(weight: torch.Tensor, bias: torch.Tensor, members: int) -> str | None:
        fp32 = weight.dtype == torch.float32 and weight.dim() == 4 and weight.shape[3] == _PANEL
        bf16 = weight.dtype == torch.bfloat16 and weight.dim() == 5 and weight.shape[3:] == (_PANEL, 2)
        if ((fp32 or bf16) and weight.shape[0] == members and weight.is_contiguous() and weight.device.type == "cpu"
                and bias.dtype == torch.float32 and bias.shape == (members, weight.shape[1] * _PANEL)
                and bias.is_contiguous()):
            return None
        return f"pack_layer's output for {members} members"

    @staticmethod
    def _in_features(weight: torch.Tensor) -> int:
        return weight.shape[2] * (2 if weight.dim() == 5 else 1)

    @staticmethod
    def _out_features(weight: torch.Tensor) -> int:
        return weight.shape[1] * _PANEL

    def __init__(self, layers: list[PackedLayer], in_features: int):
        super().__init__(layers, in_features)
        self.dtype = layers[0][0].dtype
        if any(w.dtype != self.dtype for w, _ in layers):
            raise ValueError(f"fma_network.PackedNetwork: layers in {[w.dtype for w, _ in layers]}, expected one dtype")
        first = self._in_features(layers[0][0])
        if in_features != first and not (self.dtype == torch.bfloat16 and in_features == first - 1):
            raise ValueError(f"fma_network.PackedNetwork: in_features {in_features}, expected the first layer's "
                             f"{first} (the kernel reads the input unpadded)")


def forward(x: torch.Tensor, network: PackedNetwork, out_features: int) -> torch.Tensor:
    """The network ``silu(... silu(x W_0 + b_0) ...) W_n + b_n`` of every member on the input ``x``
    ``(N, K)`` fp32 they share, the last layer's first ``out_features`` (``C``) outputs
    (:func:`~._fused_network.run`), in the packed network's dtype.

    Returns ``(L, N, C)`` fp32. fp32: within a few 1e-7 relative of torch's fp32 layers per layer
    (another summation order; the SiLU's exp polynomial). bf16: the input, the weights and the hidden
    activations rounded to bf16 (the activations computed to 1e-4 relative before rounding), fp32
    accumulation, as the AMX kernel and torch's bf16 paths compute it.
    """
    return run(_entry(network), network, x, out_features)


def prepare_forward(x: torch.Tensor, network: PackedNetwork, out_features: int, out: torch.Tensor | None = None):
    """:func:`forward` on the fixed buffers ``x`` and ``out``, prepared once
    (:func:`~._fused_network.prepare`): returns the call and its output."""
    return prepare(_entry(network), network, x, out_features, out)


def _entry(network: PackedNetwork):
    """The kernel's entry for the packed network's dtype."""
    if not available(network.dtype):
        raise RuntimeError(f"fma_network.forward: not available here in {network.dtype} ({why_not(network.dtype)})")
    return _fma_network.forward if network.dtype == torch.float32 else _fma_network.forward_bf16
