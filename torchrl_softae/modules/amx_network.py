"""The ensemble's whole network in one AMX call (``torchrl_softae/csrc/amx_network.c``), bf16.

Every member's block of 32 rows runs through all layers in AMX tiles, each hidden layer's bias
and SiLU applied to its tiles in L1, the last layer written in fp32: one call per network call
instead of five GEMM calls and four activation passes. Built at install time where a C compiler
targets AMX (an optional extension); it runs where the CPU has AMX-TILE, AMX-BF16 and
AVX512-BF16 and Linux grants the tile state (:func:`available`, :func:`why_not`). The ensemble
offers it as the inference path ``amx-network`` (bf16, SiLU) and takes it only where it
measures faster (:mod:`~torchrl_softae.modules.paths`).
"""
from __future__ import annotations

import torch

from torchrl_softae.modules._profiling import seen_by_profiler

try:  # after torch: the extension's libgomp.so.1 resolves to torch's, one OpenMP thread pool
    from torchrl_softae.modules import _amx_network
except ImportError:
    _amx_network = None

__all__ = ["available", "why_not", "cache_tag", "pack_layer", "forward", "PackedLayer", "PackedNetwork"]

#: features are padded to multiples of this (a tile's 32 bf16 inputs; two 16-column tiles)
_BLOCK = 32
#: one tile: 16 pairs of inputs x 16 outputs x 2
_TILE = (16, 32)


def available() -> bool:
    """Whether the extension was built and this CPU and OS run it."""
    return _amx_network is not None and _amx_network.available()


def why_not() -> str | None:
    """Why :func:`available` is ``False`` (``None`` where it is ``True``)."""
    if _amx_network is None:
        return "the extension torchrl_softae.modules._amx_network was not built (no C compiler targeting AMX)"
    return _amx_network.why_not()


def cache_tag() -> str | None:
    """The kernel as cached measurements name it (``None`` where it does not run)."""
    return f"revision {_amx_network.REVISION}" if available() else None


def _padded(size: int) -> int:
    return -(-size // _BLOCK) * _BLOCK


PackedLayer = tuple[torch.Tensor, torch.Tensor]


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


class PackedNetwork:
    """Every layer of an ensemble network in the kernel's layout (:func:`pack_layer`), checked
    once, with the kernel's arguments prepared: a call of :func:`forward` costs no Python per
    layer (at one-particle planning's 206 rows a network call is about 290 us, and checking and
    collecting five layers' addresses at every call had cost 23 us of it).

    Args:
        layers: :func:`pack_layer` of each layer, first to last; every layer but the last is
            followed by SiLU. The tensors are kept alive here: the kernel reads their addresses.
        in_features: the first layer's inputs before padding (:func:`forward` takes exactly
            these).
    """

    def __init__(self, layers: list[PackedLayer], in_features: int):
        if not layers:
            raise ValueError("amx_network.PackedNetwork: no layers, expected at least one")
        if not 0 < in_features <= layers[0][0].shape[2] * 32:
            raise ValueError(f"amx_network.PackedNetwork: in_features {in_features}, expected 1 to "
                             f"{layers[0][0].shape[2] * 32} (the first layer's padded inputs)")
        self.members = layers[0][0].shape[0]
        for i, (w, b) in enumerate(layers):  # the kernel reads raw addresses: only its own layout
            if not (w.dtype == torch.bfloat16 and w.dim() == 5 and w.shape[0] == self.members
                    and w.shape[3:] == _TILE and w.is_contiguous() and w.device.type == "cpu"
                    and b.dtype == torch.float32 and b.shape == (self.members, w.shape[1] * 16)
                    and b.is_contiguous()):
                raise ValueError(f"amx_network.PackedNetwork: layer {i} is {tuple(w.shape)} {w.dtype} with bias "
                                 f"{tuple(b.shape)} {b.dtype}, expected pack_layer's output for {self.members} "
                                 "members")
        for i in range(1, len(layers)):
            if layers[i][0].shape[2] * 32 != layers[i - 1][0].shape[1] * 16:
                raise ValueError(f"amx_network.PackedNetwork: layer {i} takes {layers[i][0].shape[2] * 32} padded "
                                 f"inputs, layer {i - 1} gives {layers[i - 1][0].shape[1] * 16}")
        self.layers = list(layers)
        self.in_features = in_features
        self.out_features = layers[-1][0].shape[1] * 16  # padded
        self._arguments = (tuple(w.data_ptr() for w, _ in layers), tuple(b.data_ptr() for _, b in layers),
                           tuple(w.shape[2] * 32 for w, _ in layers), tuple(w.shape[1] * 16 for w, _ in layers))

    # a copy (deepcopy, pickle) has tensors of its own: its addresses are read from them again,
    # never carried over from the original
    def __getstate__(self) -> dict:
        return {"layers": self.layers, "in_features": self.in_features}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["layers"], state["in_features"])


def forward(x: torch.Tensor, network: PackedNetwork, out_features: int) -> torch.Tensor:
    """The network ``silu(... silu(x W_0 + b_0) ...) W_n + b_n`` of every member on a shared input.

    Args:
        x: ``(N, K)`` fp32, the input all members share.
        network: the packed layers (:class:`PackedNetwork`).
        out_features: the last layer's outputs to return (its first ``C``).

    Returns:
        ``(L, N, C)`` fp32. Matmuls in bf16 with fp32 accumulation; hidden activations rounded to
        bf16 (computed to 1e-4 relative before rounding); the output is not rounded.
    """
    if not available():
        raise RuntimeError(f"amx_network.forward: not available here ({why_not()})")
    if x.dim() != 2 or x.shape[1] != network.in_features or x.dtype != torch.float32 or x.device.type != "cpu":
        raise ValueError(f"amx_network.forward: x {tuple(x.shape)} {x.dtype} on {x.device}, expected "
                         f"(N, {network.in_features}) float32 on the CPU")
    x = x.contiguous()
    out = torch.empty(network.members, x.shape[0], out_features, dtype=torch.float32)
    with seen_by_profiler("torchrl_softae::amx_network"):
        _amx_network.forward(x.data_ptr(), x.shape[0], x.shape[1], out.data_ptr(), out_features, network.members,
                             *network._arguments, torch.get_num_threads())
    return out
