"""The compiled kernels as torch.profiler sees them.

Our C extensions are called with raw pointers, outside torch's dispatcher, so ``torch.profiler``
would not see them: their time would go missing from its tables (and an op table would overstate
every other op's share). :func:`seen_by_profiler` names such a call while a profiler records and
costs one flag check otherwise.
"""
from __future__ import annotations

import contextlib

import torch

_NOT_RECORDING = contextlib.nullcontext()


def seen_by_profiler(name: str):
    """``torch.profiler.record_function(name)`` while a profiler records, else a no-op context."""
    if torch._C._autograd._profiler_enabled():  # ~50 ns: the hot path pays only this
        return torch.profiler.record_function(name)
    return _NOT_RECORDING
