"""The compiled in-place SiLU (``torchrl_softae/csrc/silu.c``) for the ensemble's inference layers.

Built at install time where a C compiler is present (an optional extension: without it
:func:`available` is ``False`` and the ensemble uses torch's SiLU). The ensemble runs it only on
an inference path that measured faster with it (``conv-silu-kernel``, ``bmm-silu-kernel`` in
:data:`~torchrl_softae.modules.paths.INFERENCE_PATHS`).
"""
from __future__ import annotations

import torch
from torch.nn import functional as F

from torchrl_softae.modules._instruction_sets import instruction_set_functions
from torchrl_softae.modules._profiling import seen_by_profiler

try:  # after torch: the extension's libgomp.so.1 resolves to torch's, one OpenMP thread pool
    from torchrl_softae.modules import _silu
except ImportError:
    _silu = None

__all__ = ["available", "isa", "supported_isas", "use_isa", "silu_"]

_DTYPE_CODES = {torch.float32: 0, torch.bfloat16: 1}


def available() -> bool:
    """Whether the extension was built and imported."""
    return _silu is not None


#: the instruction set the kernel runs on (``"avx512bf16"``, ``"avx512f"``, ``"avx2"`` or
#: ``"portable"``), the ones this CPU runs it on, and a switch between them (for tests)
isa, supported_isas, use_isa = instruction_set_functions(_silu)


def _dense(x: torch.Tensor) -> bool:
    return x.is_contiguous() or (x.dim() == 4 and x.is_contiguous(memory_format=torch.channels_last))


def silu_(x: torch.Tensor) -> torch.Tensor:
    """``x * sigmoid(x)`` in place, on torch's intra-op thread count.

    ``x``: any shape; fp32 or bf16 on the CPU in one dense block (contiguous, or a channels-last
    4-D tensor) runs the kernel, anything else ``F.silu(x, inplace=True)``. bf16 results round the
    same fp32 value as torch's; fp32 results differ from torch's by a few 1e-7 relative (its exp
    polynomial). Inference only: no autograd.
    """
    code = _DTYPE_CODES.get(x.dtype)
    if _silu is None or code is None or x.device.type != "cpu" or x.requires_grad or not _dense(x):
        return F.silu(x, inplace=True)
    with seen_by_profiler("torchrl_softae::silu_"):
        _silu.silu_(x.data_ptr(), x.numel(), code, torch.get_num_threads())
    return x
