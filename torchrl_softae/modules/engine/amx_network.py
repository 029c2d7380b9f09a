"""The ensemble's whole network in one AMX call (``torchrl_softae/modules/engine/csrc/amx_network.c``), bf16.

Every member's block of 32 rows runs through all layers in AMX tiles, each hidden layer's bias
and SiLU applied to its tiles in L1, the last layer written in fp32: one call per network call
instead of five GEMM calls and four activation passes. Built at install time where a C compiler
targets AMX (an optional extension); it runs where the CPU has AMX-TILE, AMX-BF16 and
AVX512-BF16 and Linux grants the tile state (:func:`available`, :func:`why_not`). The ensemble
offers it as the inference path ``amx-network`` (bf16, SiLU) and takes it only where it
measures faster (:mod:`~torchrl_softae.modules.engine.paths`).
"""
from __future__ import annotations

import torch

from torchrl_softae.modules.engine._fused_network import PackedLayer, PackedNetworkBase, prepare, run
from torchrl_softae.modules.engine.kernels import load_extension

_amx_network = load_extension("_amx_network")  # after torch (None: not built, or SOFTAE_KERNELS=0)

__all__ = ["RUNS", "available", "why_not", "cache_tag", "pack_layer", "pack_network", "forward", "prepare_forward",
           "PackedLayer", "PackedNetwork"]

#: features are padded to multiples of this (a tile's 32 bf16 inputs; two 16-column tiles)
_BLOCK = 32
#: one tile: 16 pairs of inputs x 16 outputs x 2
_TILE = (16, 32)


def available(dtype: torch.dtype = torch.bfloat16) -> bool:
    """Whether the extension was built and this CPU and OS run it (in ``dtype``: bf16 only)."""
    return dtype == torch.bfloat16 and _amx_network is not None and _amx_network.available()


#: what the kernel runs, for errors that name it (as :data:`.fma_network.RUNS`)
RUNS = "bf16 with nn.SiLU on an AMX CPU"


def why_not(dtype: torch.dtype = torch.bfloat16) -> str | None:
    """Why :func:`available` is ``False`` in ``dtype`` (``None`` where it is ``True``)."""
    if _amx_network is None:
        return "the extension torchrl_softae.modules.engine._amx_network was not built (no C compiler targeting AMX)"
    if dtype != torch.bfloat16:
        return f"it computes in bfloat16, not {dtype}"
    return _amx_network.why_not()


def cache_tag() -> str | None:
    """The kernel as cached measurements name it (``None`` where it does not run)."""
    return f"revision {_amx_network.REVISION}" if available() else None


def _padded(size: int) -> int:
    return -(-size // _BLOCK) * _BLOCK


def pack_layer(weight: torch.Tensor, bias: torch.Tensor) -> PackedLayer:
    """One ensemble layer in the kernel's layout.

    Args:
        weight: ``(L, K, M)`` (``x @ weight[l]`` is member ``l``'s layer), any float dtype.
        bias: ``(L, M)`` or ``(L, 1, M)``.

    Returns:
        the weight ``(L, Mp / 16, Kp / 32, 16, 32)`` bf16, each ``16 x 32`` block one AMX tile in
        its pair-interleaved form (``[r, 2 j + t]`` is input ``32 kb + 2 r + t``, output
        ``16 nb + j``), and the bias ``(L, Mp)`` fp32; ``Kp``, ``Mp``: ``K``, ``M`` padded with
        zeros to multiples of 32.
    """
    members, k, m = weight.shape
    kp, mp = _padded(k), _padded(m)
    w = torch.zeros(members, kp, mp, dtype=torch.bfloat16, device=weight.device)
    w[:, :k, :m] = weight
    # (L, kb, r, t, nb, j) -> (L, nb, kb, r, j, t): tile (nb, kb) holds W[32 kb + 2 r + t, 16 nb + j]
    w = w.view(members, kp // 32, 16, 2, mp // 16, 16).permute(0, 4, 1, 2, 5, 3).contiguous()
    b = torch.zeros(members, mp, dtype=torch.float32, device=weight.device)
    b[:, :m] = bias.reshape(members, m)
    return w.view(members, mp // 16, kp // 32, *_TILE), b


class PackedNetwork(PackedNetworkBase):
    """Every layer of an ensemble network in the kernel's layout (:func:`pack_layer`), checked
    once, with the kernel's arguments prepared (:class:`~._fused_network.PackedNetworkBase`).
    ``in_features`` may be less than the first layer's padded inputs: the kernel pads the input."""

    kernel = "amx_network"

    @staticmethod
    def _layer_error(weight: torch.Tensor, bias: torch.Tensor, members: int) -> str | None:
        if (weight.dtype == torch.bfloat16 and weight.dim() == 5 and weight.shape[0] == members
                and weight.shape[3:] == _TILE and weight.is_contiguous() and weight.device.type == "cpu"
                and bias.dtype == torch.float32 and bias.shape == (members, weight.shape[1] * 16)
                and bias.is_contiguous()):
            return None
        return f"pack_layer's output for {members} members"

    @staticmethod
    def _in_features(weight: torch.Tensor) -> int:
        return weight.shape[2] * 32

    @staticmethod
    def _out_features(weight: torch.Tensor) -> int:
        return weight.shape[1] * 16


def pack_network(layers: list[tuple[torch.Tensor, torch.Tensor]], dtype: torch.dtype = torch.bfloat16
                 ) -> PackedNetwork:
    """A whole network, ``[(weight (L, K, M), bias), ...]`` first to last, packed (each layer's
    inputs and outputs padded to multiples of 32, so each takes the previous one's outputs).
    ``dtype``: the kernel computes in bf16 only."""
    if dtype != torch.bfloat16:
        raise ValueError(f"amx_network.pack_network: dtype={dtype}, expected torch.bfloat16 (AMX tiles)")
    return PackedNetwork([pack_layer(w, b) for w, b in layers], layers[0][0].shape[1])


def forward(x: torch.Tensor, network: PackedNetwork, out_features: int) -> torch.Tensor:
    """The network ``silu(... silu(x W_0 + b_0) ...) W_n + b_n`` of every member on the input ``x``
    ``(N, K)`` fp32 they share, the last layer's first ``out_features`` (``C``) outputs
    (:func:`~._fused_network.run`).

    Returns ``(L, N, C)`` fp32: matmuls in bf16 with fp32 accumulation, hidden activations rounded
    to bf16 (computed to 1e-4 relative before rounding); the output is not rounded.
    """
    return run(_entry(), network, x, out_features)


def prepare_forward(x: torch.Tensor, network: PackedNetwork, out_features: int, out: torch.Tensor | None = None):
    """:func:`forward` on the fixed buffers ``x`` and ``out``, prepared once
    (:func:`~._fused_network.prepare`): returns the call and its output."""
    return prepare(_entry(), network, x, out_features, out)


def _entry():
    """The kernel's entry, where it runs."""
    if not available():
        raise RuntimeError(f"amx_network.forward: not available here ({why_not()})")
    return _amx_network.forward
