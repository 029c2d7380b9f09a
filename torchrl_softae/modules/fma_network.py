"""The ensemble's whole network in one fp32 call (``torchrl_softae/csrc/fma_network.c``).

Every member's block of up to 12 rows (AVX-512; 6 with AVX2) runs through all layers in FMA
register blocks, each hidden layer's bias and SiLU applied in registers, the last layer written
out: one call per network call instead of five GEMM calls and four activation passes. Built at
install time where a C compiler is present (an optional extension); it runs where the CPU has
AVX-512F or AVX2 with FMA (:func:`available`, :func:`isa`). The ensemble offers it as the
inference path ``fma-network`` (fp32, SiLU) and takes it only where it measures faster
(:mod:`~torchrl_softae.modules.paths`).
"""
from __future__ import annotations

import torch

from torchrl_softae.modules._fused_network import PackedLayer, PackedNetworkBase, run
from torchrl_softae.modules._instruction_sets import instruction_set_functions

try:  # after torch: the extension's libgomp.so.1 resolves to torch's, one OpenMP thread pool
    from torchrl_softae.modules import _fma_network
except ImportError:
    _fma_network = None

__all__ = ["available", "why_not", "isa", "supported_isas", "use_isa", "cache_tag", "pack_layer", "pack_network",
           "forward", "PackedLayer", "PackedNetwork"]

#: output columns per packed weight panel (two AVX-512 registers, four AVX2 ones)
_PANEL = 32

#: the instruction set the kernel runs on (``"avx512f"`` or ``"avx2"``), the ones this CPU runs it
#: on, and a switch between them (for tests)
isa, supported_isas, use_isa = instruction_set_functions(_fma_network)


def available() -> bool:
    """Whether the extension was built and this CPU runs it."""
    return _fma_network is not None and isa() is not None


def why_not() -> str | None:
    """Why :func:`available` is ``False`` (``None`` where it is ``True``)."""
    if _fma_network is None:
        return "the extension torchrl_softae.modules._fma_network was not built (no C compiler)"
    return None if available() else "the CPU has neither AVX-512F nor AVX2 with FMA"


def cache_tag() -> str | None:
    """The kernel as cached measurements name it: its instruction set and revision (``None``
    where it does not run)."""
    return f"{isa()} revision {_fma_network.REVISION}" if available() else None


def pack_layer(weight: torch.Tensor, bias: torch.Tensor, inputs: int | None = None) -> PackedLayer:
    """One ensemble layer in the kernel's layout.

    Args:
        weight: ``(L, K, M)`` (``x @ weight[l]`` is member ``l``'s layer), any float dtype.
        bias: ``(L, M)`` or ``(L, 1, M)``.
        inputs: the packed layer's inputs, ``K`` or more (zero rows beyond ``K``): a hidden
            layer takes the previous layer's padded outputs. Default ``K``.

    Returns:
        the weight ``(L, Mp / 32, inputs, 32)`` fp32, panel ``p`` holding ``W[k, 32 p + j]``
        (zeros where ``32 p + j >= M`` or ``k >= K``), and the bias ``(L, Mp)`` fp32; ``Mp``:
        ``M`` padded to a multiple of 32.
    """
    members, k, m = weight.shape
    inputs = k if inputs is None else inputs
    if inputs < k:
        raise ValueError(f"fma_network.pack_layer: inputs={inputs}, expected at least the weight's {k}")
    mp = -(-m // _PANEL) * _PANEL
    w = torch.zeros(members, inputs, mp, dtype=torch.float32, device=weight.device)
    w[:, :k, :m] = weight
    w = w.view(members, inputs, mp // _PANEL, _PANEL).permute(0, 2, 1, 3).contiguous()
    b = torch.zeros(members, mp, dtype=torch.float32, device=weight.device)
    b[:, :m] = bias.reshape(members, m)
    return w, b


def pack_network(layers: list[tuple[torch.Tensor, torch.Tensor]]) -> "PackedNetwork":
    """A whole network, ``[(weight (L, K, M), bias), ...]`` first to last, packed: each hidden
    layer takes the previous one's padded outputs, the first the unpadded input."""
    packed: list[PackedLayer] = []
    for w, b in layers:
        packed.append(pack_layer(w, b, None if not packed else packed[-1][0].shape[1] * _PANEL))
    return PackedNetwork(packed, layers[0][0].shape[1])


class PackedNetwork(PackedNetworkBase):
    """Every layer of an ensemble network in the kernel's layout (:func:`pack_layer`), checked
    once, with the kernel's arguments prepared (:class:`~._fused_network.PackedNetworkBase`).
    ``in_features`` must equal the first layer's ``K``: the kernel reads the input unpadded."""

    kernel = "fma_network"

    @staticmethod
    def _layer_error(weight: torch.Tensor, bias: torch.Tensor, members: int) -> str | None:
        if (weight.dtype == torch.float32 and weight.dim() == 4 and weight.shape[0] == members
                and weight.shape[3] == _PANEL and weight.is_contiguous() and weight.device.type == "cpu"
                and bias.dtype == torch.float32 and bias.shape == (members, weight.shape[1] * _PANEL)
                and bias.is_contiguous()):
            return None
        return f"pack_layer's output for {members} members"

    @staticmethod
    def _in_features(weight: torch.Tensor) -> int:
        return weight.shape[2]

    @staticmethod
    def _out_features(weight: torch.Tensor) -> int:
        return weight.shape[1] * _PANEL

    def __init__(self, layers: list[PackedLayer], in_features: int):
        super().__init__(layers, in_features)
        if in_features != layers[0][0].shape[2]:
            raise ValueError(f"fma_network.PackedNetwork: in_features {in_features}, expected the first layer's "
                             f"{layers[0][0].shape[2]} (the kernel reads the input unpadded)")


def forward(x: torch.Tensor, network: PackedNetwork, out_features: int) -> torch.Tensor:
    """The network ``silu(... silu(x W_0 + b_0) ...) W_n + b_n`` of every member on the input ``x``
    ``(N, K)`` fp32 they share, the last layer's first ``out_features`` (``C``) outputs
    (:func:`~._fused_network.run`).

    Returns ``(L, N, C)`` fp32, within a few 1e-7 relative of torch's fp32 layers per layer (another
    summation order; the SiLU's exp polynomial).
    """
    if not available():
        raise RuntimeError(f"fma_network.forward: not available here ({why_not()})")
    return run(_fma_network, network, x, out_features)
