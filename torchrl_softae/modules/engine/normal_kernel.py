"""Counter-based standard normal draws for planning (``torchrl_softae/modules/engine/csrc/normal.c``).

The aleatoric noise of PETS-style propagation and the colored noise of iCEM's candidates are drawn
at every model step, and torch's CPU generator (mt19937) draws on one thread: in a bf16 plan
those draws can be the largest op after the network. Here a value is a pure function of a 64-bit
seed and its index (SplitMix64 of the counter, Box-Muller), computed on torch's threads;
the seed is one value drawn from the caller's ``torch.Generator``, so a seeded generator gives a
seeded stream, as with ``torch.randn`` (but not the same values). Every instruction-set variant
and every thread count gives the same bits.

Built at install time where a C compiler is present (an optional extension); where it is not
built, on a CPU without AVX2 (where its portable C is slower than ``torch.randn``), or for tensors
it does not take (not fp32 on the CPU), ``torch.randn`` draws instead. Speeds by instruction
set: ``benchmarks/README.md``.
"""
from __future__ import annotations


import torch

from torchrl_softae.modules.engine._instruction_sets import instruction_set_functions
from torchrl_softae.modules.engine._profiling import seen_by_profiler
from torchrl_softae.modules.engine.kernels import load_extension

_normal = load_extension("_normal")  # after torch (None: not built, or SOFTAE_KERNELS=0)
if _normal is not None and _normal.supported_isas()[-1] == "portable":
    # without AVX2 the portable C (a libm call per fused multiply-add) is slower than
    # torch.randn: draw with torch there
    _normal = None

__all__ = ["available", "applies", "randn", "normal_", "add_scaled_randn", "isa", "supported_isas", "use_isa"]

#: ``"avx512"``, ``"avx2"`` or ``"portable"`` (the same values on each), the ones this CPU runs, a switch
isa, supported_isas, use_isa = instruction_set_functions(_normal)


def available() -> bool:
    """Whether the extension was built and this CPU runs one of its vector variants."""
    return _normal is not None


def _kernel_draws(dtype: torch.dtype, device, generator: torch.Generator | None) -> bool:
    """Whether draws of ``dtype`` on ``device`` from ``generator`` come from the kernel: fp32 on
    the CPU, a CPU generator or the default one, the kernel built."""
    return (_normal is not None and dtype == torch.float32 and torch.device(device).type == "cpu"
            and (generator is None or generator.device.type == "cpu"))


def applies(like: torch.Tensor, generator: torch.Generator | None = None) -> bool:
    """Whether :func:`randn` / :func:`add_scaled_randn` draw with the kernel for tensors like
    ``like`` (fp32 on the CPU, no autograd) and ``generator`` (a CPU one, or the default): where
    it was built."""
    return not like.requires_grad and _kernel_draws(like.dtype, like.device, generator)


def _seed(generator: torch.Generator | None) -> int:
    """The stream's seed: one 63-bit value drawn from ``generator`` (torch's default without one)."""
    return int(torch.randint(0, 2**63 - 1, (), generator=generator))


def randn(shape: tuple[int, ...], generator: torch.Generator | None = None, dtype: torch.dtype = torch.float32,
          device=None) -> torch.Tensor:
    """``shape`` standard normal values: fp32 on the CPU (with a CPU generator or none) from the
    kernel, the stream of one seed drawn from ``generator``; any other dtype or device from
    ``torch.randn``."""
    if not _kernel_draws(dtype, device or "cpu", generator):
        return torch.randn(shape, generator=generator, dtype=dtype, device=device)
    return normal_(torch.empty(shape, dtype=torch.float32), generator)


def normal_(out: torch.Tensor, generator: torch.Generator | None = None, kernel: bool = True) -> torch.Tensor:
    """Fills the contiguous tensor ``out`` in place with the values ``randn(out.shape, generator,
    out.dtype, out.device)`` would return (a planning rollout draws its steps' noise into its own
    buffer, the generator consumed as by one draw per step); ``kernel=False``: ``torch.randn``'s.
    Returns ``out``."""
    if not out.is_contiguous():
        raise ValueError(f"normal_: out has strides {out.stride()}, expected a contiguous tensor")
    if not kernel or not _kernel_draws(out.dtype, out.device, generator):
        return out.copy_(torch.randn(out.shape, generator=generator, dtype=out.dtype, device=out.device))
    with seen_by_profiler("torchrl_softae::randn"):
        _normal.fill(out.data_ptr(), 0, 0, out.numel(), _seed(generator), torch.get_num_threads())
    return out


def add_scaled_randn(x: torch.Tensor, std: torch.Tensor, generator: torch.Generator | None = None,
                     kernel: bool = True) -> torch.Tensor:
    """``x + std * z``, ``z`` standard normal of ``x``'s shape, in one pass (a new tensor).

    Args:
        x: ``(*B, d)``; std: broadcastable to ``x``.
        generator: the seed's source.
        kernel: ``False`` for torch's draws whatever :func:`applies` says (a model built with
            ``kernels="torch"``).

    Where :func:`applies` does not hold for ``x``, ``x + std * torch.randn(...)``.
    """
    if not kernel or not applies(x, generator) or std.dtype != torch.float32 or std.device != x.device:
        return x + std * torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)
    x = x.contiguous()
    std = std.expand_as(x).contiguous()
    out = torch.empty_like(x)
    with seen_by_profiler("torchrl_softae::add_scaled_randn"):
        _normal.fill(out.data_ptr(), x.data_ptr(), std.data_ptr(), out.numel(), _seed(generator),
                     torch.get_num_threads())
    return out
