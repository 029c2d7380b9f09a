"""Keep freed CPU memory for reuse: no page faults on every large tensor a planner allocates.

PyTorch allocates CPU tensors with the C library's ``malloc``. glibc's ``malloc`` gives every
allocation above its mmap threshold (at most 32 MiB) its own mapping and unmaps it when freed, and
returns freed memory at the top of its heap to the kernel once more than a threshold (twice the
mmap threshold) is free. Either way the next allocation of that size touches fresh pages, and the
kernel faults in and zeroes every 4 KiB of them. An ensemble's hidden layer at a 10-particle
plan's 2060 rows is 10.5 MiB (fp32), at the rows of 8 such plans as one batch 84 MiB.

Whether a plan faults depends on what the process allocated before (glibc's thresholds move
with it), so the gain varies from run to run; above 32 MiB every allocation faults. Measured:
``benchmarks/studies/allocator_speed.py`` (numbers in ``benchmarks/README.md``).

:func:`keep_freed_memory` tells glibc to serve every allocation from its heap and to keep freed
memory for the next allocation, as PyTorch's CPU launcher (``torch.backends.xeon.run_cpu``) does
with jemalloc's decay settings. It is process-wide, so the library never calls it on its own; the
``softae`` commands and the benchmarks do. The cost: freed memory stays with the process (a few
times the largest tensor that is allocated again and again: peak memory 887 against 588 MiB for
the 84 MiB network call, unchanged for plans). The first few allocations of a size still fault
(2 to 10 of a 64 MiB tensor allocated again and again, measured in fresh processes): the small
objects allocated between them pin them until glibc's heap settles.
"""
from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["keep_freed_memory"]

# mallopt parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4

#: freed memory the process keeps for reuse by default (the machines of this project have 24 GiB)
DEFAULT_RETAINED_BYTES = 1 << 30


def _glibc_malloc():
    """glibc's ``libc`` when its ``malloc`` is the process's (not interposed by jemalloc,
    tcmalloc, ...), else ``None``."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
        libc.gnu_get_libc_version  # glibc only  # noqa: B018
        process = ctypes.CDLL(None)
    except (OSError, AttributeError):
        return None
    address = lambda lib: ctypes.cast(lib.malloc, ctypes.c_void_p).value  # noqa: E731
    return libc if address(libc) == address(process) else None


def keep_freed_memory(retain_bytes: int = DEFAULT_RETAINED_BYTES) -> bool:
    """Serve every allocation from glibc's heap and keep up to ``retain_bytes`` of freed memory.

    Returns ``True`` when applied; ``False`` where ``malloc`` is not glibc's (macOS, musl, or an
    allocator preloaded with ``LD_PRELOAD``, which has its own settings). Applies to allocations
    from the process's main thread (glibc's main arena), where tensors of a planner live.
    """
    # mallopt takes an int: glibc cannot be told to keep more than 2 GiB
    if not isinstance(retain_bytes, int) or isinstance(retain_bytes, bool) or not 0 <= retain_bytes < 2**31:
        raise ValueError(f"keep_freed_memory: retain_bytes={retain_bytes!r}, expected an int in [0, 2**31)")
    libc = _glibc_malloc()
    if libc is None:
        return False
    libc.mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    return bool(libc.mallopt(_M_MMAP_MAX, 0)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, retain_bytes))
