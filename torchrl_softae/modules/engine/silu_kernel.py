"""The compiled in-place SiLU (``torchrl_softae/modules/engine/csrc/silu.c``) for the ensemble's inference layers.

Built at install time where a C compiler is present (an optional extension: without it
:func:`available` is ``False`` and the ensemble uses torch's SiLU). The ensemble runs it only on
an inference path that measured faster with it (``conv-silu-kernel``, ``bmm-silu-kernel`` in
:data:`~torchrl_softae.modules.engine.paths.INFERENCE_PATHS`).
"""
from __future__ import annotations

import torch
from torch.nn import functional as F

from torchrl_softae.modules.engine._instruction_sets import instruction_set_functions
from torchrl_softae.modules.engine._profiling import seen_by_profiler
from torchrl_softae.modules.engine.kernels import load_extension

_silu = load_extension("_silu")  # after torch (None: not built, or SOFTAE_KERNELS=0)

__all__ = ["available", "isa", "supported_isas", "use_isa", "cache_tag", "silu_", "bias_silu_"]

_DTYPE_CODES = {torch.float32: 0, torch.bfloat16: 1}


def available() -> bool:
    """Whether the extension was built and imported."""
    return _silu is not None


#: the instruction set the kernel runs on (``"avx512bf16"``, ``"avx512f"``, ``"avx2"`` or
#: ``"portable"``), the ones this CPU runs it on, and a switch between them (for tests)
isa, supported_isas, use_isa = instruction_set_functions(_silu)


def cache_tag() -> str | None:
    """The kernel as cached measurements name it: its instruction set and revision (``None``
    where it was not built). A rebuilt kernel that computes differently has a new revision, so
    the inference paths measured with the old one are measured again."""
    return None if _silu is None else f"{isa()} revision {_silu.REVISION}"


def _dense(x: torch.Tensor) -> bool:
    return x.is_contiguous() or (x.dim() == 4 and x.is_contiguous(memory_format=torch.channels_last))


def _runs_kernel(x: torch.Tensor) -> bool:
    return (_silu is not None and x.dtype in _DTYPE_CODES and x.device.type == "cpu" and not x.requires_grad
            and _dense(x))


def silu_(x: torch.Tensor) -> torch.Tensor:
    """``x * sigmoid(x)`` in place, on torch's intra-op thread count.

    ``x``: any shape; fp32 or bf16 on the CPU in one dense block (contiguous, or a channels-last
    4-D tensor) runs the kernel, anything else ``F.silu(x, inplace=True)``. fp32 results differ
    from torch's by a few 1e-7 relative (its exp polynomial). bf16 results are torch's or one bf16
    ulp from it: on AVX-512 the kernel computes them to 1e-4 relative, not to fp32 precision,
    so values next to a rounding boundary may round the other way. Inference only: no autograd.
    """
    if not _runs_kernel(x):
        return F.silu(x, inplace=True)
    with seen_by_profiler("torchrl_softae::silu_"):
        _silu.silu_(x.data_ptr(), 1, 1, x.numel(), 0, _DTYPE_CODES[x.dtype], torch.get_num_threads())
    return x


def bias_silu_(x: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``silu(x + bias)`` in place, the bias added in fp32 before the activation: a layer's
    activation fused with its bias, after a matmul without one.

    Args:
        x: ``(G, N, C)`` or ``(N, C)`` (one group), fp32 or bf16.
        bias: fp32, ``(G, 1, C)``, ``(G, C)`` or ``(C,)``: group ``g``'s row added to each of
            ``x[g]``'s ``N`` rows (a 1-D bias to every row of every group).

    Where the kernel does not run (see :func:`silu_`), torch's ops give the same result.
    Inference only: no autograd.
    """
    if x.dim() == 2:
        x3 = x.unsqueeze(0)
    elif x.dim() == 3:
        x3 = x
    else:
        raise ValueError(f"bias_silu_: x of shape {tuple(x.shape)}, expected (G, N, C) or (N, C)")
    groups, _, cols = x3.shape
    rows_of_bias = bias.reshape(-1, cols) if cols > 0 and bias.numel() % cols == 0 else None
    if bias.dtype != torch.float32 or rows_of_bias is None or rows_of_bias.shape[0] not in (1, groups):
        raise ValueError(f"bias_silu_: bias {tuple(bias.shape)} {bias.dtype}, expected fp32 with {cols} values "
                         f"per row for {groups} group(s) (or one row for all)")
    if not _runs_kernel(x3) or rows_of_bias.device != x3.device:
        x3.copy_(F.silu(x3.float() + rows_of_bias.to(x3.device).unsqueeze(1)))
        return x
    rows_of_bias = rows_of_bias.contiguous()
    if rows_of_bias.shape[0] == 1 and groups > 1:  # one row for all groups: one block of G * N rows
        shape = (1, groups * x3.shape[1], cols)
    else:
        shape = x3.shape
    with seen_by_profiler("torchrl_softae::bias_silu_"):
        _silu.silu_(x3.data_ptr(), shape[0], shape[1], shape[2], rows_of_bias.data_ptr(), _DTYPE_CODES[x.dtype],
                    torch.get_num_threads())
    return x
