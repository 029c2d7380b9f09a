"""What the two whole-network kernels share (:mod:`.amx_network`, bf16 AMX tiles;
:mod:`.fma_network`, fp32 FMA register blocks): layers packed once in a kernel's own layout,
checked once, with the kernel's arguments prepared, and one call per network call."""
from __future__ import annotations

from typing import Callable

import torch

from torchrl_softae.modules.engine._profiling import seen_by_profiler

PackedLayer = tuple[torch.Tensor, torch.Tensor]


class PackedNetworkBase:
    """Every layer of an ensemble network in a kernel's layout, checked once, with the kernel's
    arguments prepared: a network call costs no Python per layer (checking and collecting the
    layers' addresses at every call is a visible part of a small network call).

    Subclasses name the kernel (``kernel``) and say how a packed layer reads:
    :meth:`_layer_error` (``None`` for the kernel's own layout), :meth:`_in_features` and
    :meth:`_out_features` (padded as the kernel takes them).

    Args:
        layers: the kernel's ``pack_layer`` of each layer, first to last; every layer but the last
            is followed by SiLU. The tensors are kept alive here: the kernel reads their addresses.
        in_features: the first layer's inputs before padding (the kernel's ``forward`` takes
            exactly these).
    """

    kernel = "fused_network"

    @staticmethod
    def _layer_error(weight: torch.Tensor, bias: torch.Tensor, members: int) -> str | None:
        raise NotImplementedError

    @staticmethod
    def _in_features(weight: torch.Tensor) -> int:
        raise NotImplementedError

    @staticmethod
    def _out_features(weight: torch.Tensor) -> int:
        raise NotImplementedError

    def __init__(self, layers: list[PackedLayer], in_features: int):
        name = f"{self.kernel}.PackedNetwork"
        if not layers:
            raise ValueError(f"{name}: no layers, expected at least one")
        first_in = self._in_features(layers[0][0])
        if not 0 < in_features <= first_in:
            raise ValueError(f"{name}: in_features {in_features}, expected 1 to {first_in} (the first layer's "
                             "inputs as packed)")
        self.members = layers[0][0].shape[0]
        for i, (w, b) in enumerate(layers):  # the kernel reads raw addresses: only its own layout
            error = self._layer_error(w, b, self.members)
            if error is not None:
                raise ValueError(f"{name}: layer {i} is {tuple(w.shape)} {w.dtype} with bias {tuple(b.shape)} "
                                 f"{b.dtype}, expected {error}")
        for i in range(1, len(layers)):
            if self._in_features(layers[i][0]) != self._out_features(layers[i - 1][0]):
                raise ValueError(f"{name}: layer {i} takes {self._in_features(layers[i][0])} inputs as packed, "
                                 f"layer {i - 1} gives {self._out_features(layers[i - 1][0])}")
        self.layers = list(layers)
        self.in_features = in_features
        self.out_features = self._out_features(layers[-1][0])  # padded
        self._arguments = (tuple(w.data_ptr() for w, _ in layers), tuple(b.data_ptr() for _, b in layers),
                           tuple(self._in_features(w) for w, _ in layers),
                           tuple(self._out_features(w) for w, _ in layers))

    # a copy (deepcopy, pickle) has tensors of its own: its addresses are read from them again,
    # never carried over from the original
    def __getstate__(self) -> dict:
        return {"layers": self.layers, "in_features": self.in_features}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["layers"], state["in_features"])


def prepare(kernel: Callable, network: PackedNetworkBase, x: torch.Tensor, out_features: int,
            out: torch.Tensor | None = None) -> tuple[Callable[[], None], torch.Tensor]:
    """One call of a whole-network kernel on fixed buffers, checked and with its arguments
    prepared once: a planning rollout runs it at every step with nothing else in Python.

    Args:
        kernel: the compiled kernel's entry (it takes the addresses of ``x``, the output and
            ``network``'s packed layers, csrc/whole_network.h).
        network: the packed layers.
        x: ``(N, network.in_features)`` contiguous fp32 on the CPU, the input every member
            shares. The call reads it where it lies: the caller keeps it alive and writes it in
            place.
        out_features: the last layer's outputs to compute (its first ``C``).
        out: ``(L, N, C)`` contiguous fp32 to write (a new tensor if ``None``).

    Returns:
        the call (no arguments; the output is written in place) and ``out``.
    """
    if (x.dim() != 2 or x.shape[1] != network.in_features or x.dtype != torch.float32 or x.device.type != "cpu"
            or not x.is_contiguous()):
        raise ValueError(f"{network.kernel}.forward: x {tuple(x.shape)} {x.dtype} on {x.device}, expected "
                         f"(N, {network.in_features}) float32 on the CPU, contiguous")
    shape = (network.members, x.shape[0], out_features)
    if out is None:
        out = torch.empty(shape, dtype=torch.float32)
    elif tuple(out.shape) != shape or out.dtype != torch.float32 or not out.is_contiguous() or out.device.type != "cpu":
        raise ValueError(f"{network.kernel}.forward: out {tuple(out.shape)} {out.dtype}, expected {shape} contiguous "
                         "float32 on the CPU")
    # the threads: as many as torch's at preparation
    arguments = (x.data_ptr(), x.shape[0], x.shape[1], out.data_ptr(), out_features, network.members,
                 *network._arguments, torch.get_num_threads())
    name = f"torchrl_softae::{network.kernel}"

    def call(alive=(x, out, network)) -> None:  # kept alive with the call: it reads their addresses
        with seen_by_profiler(name):
            kernel(*arguments)

    return call, out


def run(kernel: Callable, network: PackedNetworkBase, x: torch.Tensor, out_features: int) -> torch.Tensor:
    """One call of a whole-network kernel (:func:`prepare`, run at once).

    Args:
        kernel: the compiled kernel's entry.
        network: the packed layers.
        x: ``(N, network.in_features)`` fp32 on the CPU, the input every member shares.
        out_features: the last layer's outputs to return (its first ``C``).

    Returns:
        ``(L, N, C)`` fp32.
    """
    call, out = prepare(kernel, network, x.contiguous(), out_features)
    call()
    return out
