"""The compiled one-pass ensemble moments (``torchrl_softae/modules/engine/csrc/moments.c``) for planning.

From the ensemble's raw output (normalized member deltas, in the planner's dtype, read where they
lie in the network's output buffer) it computes the mean [mu] and epistemic std [sigma] of the
member means, and for trajectory sampling one member's mean and raw log-variance per row, without
materializing the ``(L, N, d_s)`` member means. Built at install time where a C compiler is
present (an optional extension: without it :func:`available` is ``False`` and
:class:`~torchrl_softae.modules.EnsembleWorldModel` runs the same arithmetic as torch ops).
"""
from __future__ import annotations

from typing import Callable

import torch

from torchrl_softae.modules.engine._instruction_sets import instruction_set_functions
from torchrl_softae.modules.engine._profiling import seen_by_profiler
from torchrl_softae.modules.engine.kernels import load_extension

_moments = load_extension("_moments")  # after torch (None: not built, or SOFTAE_KERNELS=0)
if _moments is not None and not _moments.supported():  # built, but this CPU lacks AVX2
    _moments = None

#: members the kernel keeps in registers (``MAX_VECTOR_MEMBERS`` in moments.c); 0 without the kernel
MAX_MEMBERS = 0 if _moments is None else _moments.MAX_MEMBERS

__all__ = ["MAX_MEMBERS", "MAX_LOGVAR_SPAN", "available", "applies", "ensemble_moments", "prepare_moments", "isa",
           "supported_isas", "use_isa"]

_DTYPE_CODES = {torch.float32: 0, torch.bfloat16: 1}


#: the widest log-variance bounds (max - min) the fused aleatoric std takes: exp(span) stays finite
MAX_LOGVAR_SPAN = 80.0


def available() -> bool:
    """Whether the extension was built and runs on this CPU (AVX2, or AVX-512 F, BW and VL)."""
    return _moments is not None


#: the instruction set the kernel runs on (``"avx512"`` or ``"avx2"``), the ones this CPU runs it
#: on, and a switch between them (for tests)
isa, supported_isas, use_isa = instruction_set_functions(_moments)


def applies(output: torch.Tensor) -> bool:
    """Whether :func:`ensemble_moments` can run on this ``(L, N, C)`` network ``output`` (CPU, fp32
    or bf16, unit stride along ``C``, at most :data:`MAX_MEMBERS` members, no autograd)."""
    return (_moments is not None and output.device.type == "cpu" and output.dtype in _DTYPE_CODES
            and output.dim() == 3 and output.shape[0] <= MAX_MEMBERS and output.stride(-1) == 1
            and not output.requires_grad)


def ensemble_moments(
    output: torch.Tensor, state: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor, d: int,
    member_index: torch.Tensor | None = None, with_logvar: bool = False,
    logvar_bounds: tuple[torch.Tensor, torch.Tensor] | None = None, eta: torch.Tensor | None = None,
    next_input: torch.Tensor | None = None, input_loc: torch.Tensor | None = None,
    input_scale: torch.Tensor | None = None, noise: torch.Tensor | None = None, particles: int = 1,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """Moments of the member means ``m_l = state + loc + scale * output[l, :, :d]``
    (:func:`prepare_moments`, run at once; its arguments)."""
    call, outputs = prepare_moments(output, state, loc, scale, d, member_index, with_logvar, logvar_bounds, eta,
                                    next_input, input_loc, input_scale, noise=noise, particles=particles)
    call()
    return outputs


def prepare_moments(
    output: torch.Tensor, state: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor, d: int,
    member_index: torch.Tensor | None = None, with_logvar: bool = False,
    logvar_bounds: tuple[torch.Tensor, torch.Tensor] | None = None, eta: torch.Tensor | None = None,
    next_input: torch.Tensor | None = None, input_loc: torch.Tensor | None = None,
    input_scale: torch.Tensor | None = None, out: tuple[torch.Tensor, torch.Tensor] | None = None,
    noise: torch.Tensor | None = None, particles: int = 1,
) -> tuple[Callable[[], None], tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]]:
    """Moments of the member means ``m_l = state + loc + scale * output[l, :, :d]``: the kernel's
    call on these buffers, checked and with its arguments prepared once (a planning rollout runs
    it at every step with nothing else in Python), and the outputs it writes. The call reads its
    inputs where they lie when it runs (``member_index`` is checked here).

    Args:
        output: ``(L, N / particles, C)`` raw network output, fp32 or bf16, any member and row
            strides (unit stride along ``C``); the normalized delta means are its first ``d``
            columns and, with ``with_logvar``, the raw log-variances the next ``d``.
        state: ``(N / particles, d)`` the state in the model's space; loc, scale: ``(d,)`` the
            output normalizer.
        member_index: ``(N,)`` int64, the member each row follows (trajectory sampling), or ``None``.
        logvar_bounds: ``(min_logvar, max_logvar)``, ``(d,)`` each (the PETS soft bounds): with
            ``member_index`` and ``with_logvar``, return that member's aleatoric std in the model's
            units, ``scale * exp(v / 2)`` of its bounded log-variance ``v``, instead of the raw
            log-variance (one exp per value where the torch ops make nine passes). Needs
            ``max_logvar - min_logvar <`` :data:`MAX_LOGVAR_SPAN` (else ``exp`` overflows in fp32).
        eta: ``(N, d)`` fp32, the hallucinated control times beta: the first output is then
            ``mu + sigma * eta`` (SoftAE's optimistic next state) instead of ``mu``.
        next_input: ``(N, K)`` fp32 with unit column stride, ``K >= d``: its first ``d`` columns
            receive the first output normalized, ``(out - input_loc) / input_scale`` (``(d,)``
            each): the state columns of the next step's network input.
        noise: ``(N, d)`` fp32 standard normal draws, with ``member_index``: the first output is
            then that member's sampled next state, its mean plus its aleatoric std times ``noise``
            (the mean alone without ``with_logvar``: deterministic members), PETS' trajectory
            sampling. Needs ``logvar_bounds`` with ``with_logvar``; not with ``eta``. The member's
            mean and std are then not returned.
        particles: output rows per row of ``output`` and ``state``: row ``n`` of the results is
            computed from their row ``n // particles`` (a candidate's particles at the first step
            of a plan share its state and action, so the network ran once for them).
        out: ``(mu, sigma)`` to write, ``(N, d)`` contiguous fp32 each (new tensors if ``None``).

    Returns:
        The call, and ``mu`` (or ``mu + sigma * eta``, or the sampled next state) and ``sigma``
        ``(N, d)`` [mu, sigma; sigma with Bessel's correction], and with ``member_index`` (without
        ``noise``) that member's mean and (with ``with_logvar``) raw log-variance or aleatoric std
        ``(N, d)``, else ``None``. All fp32. Only where :func:`applies` holds.
    """
    L, sources, cols = output.shape
    if cols < (2 * d if with_logvar else d):
        raise ValueError(f"ensemble_moments: output has {cols} columns, expected at least {2 * d if with_logvar else d}")
    if particles < 1:
        raise ValueError(f"ensemble_moments: particles={particles}, expected >= 1")
    n = sources * particles
    state, loc, scale = (_fp32(t) for t in (state, loc.reshape(d), scale.reshape(d)))
    if state.shape != (sources, d):
        raise ValueError(f"ensemble_moments: state has shape {tuple(state.shape)}, expected ({sources}, {d})")
    eta_address = noise_address = next_address = next_stride = in_loc_address = in_scale_address = 0
    if eta is not None:
        eta = _fp32(eta)
        if eta.shape != (n, d):
            raise ValueError(f"ensemble_moments: eta has shape {tuple(eta.shape)}, expected ({n}, {d})")
        eta_address = eta.data_ptr()
    if noise is not None:
        if member_index is None or eta is not None or (with_logvar and logvar_bounds is None):
            raise ValueError("ensemble_moments: noise needs member_index (and logvar_bounds with with_logvar), "
                             "and no eta")
        noise = _fp32(noise)
        if noise.shape != (n, d):
            raise ValueError(f"ensemble_moments: noise has shape {tuple(noise.shape)}, expected ({n}, {d})")
        noise_address = noise.data_ptr()
    if next_input is not None:
        if (next_input.dim() != 2 or next_input.shape[0] != n or next_input.shape[1] < d or next_input.stride(1) != 1
                or next_input.dtype != torch.float32 or next_input.device.type != "cpu"):
            raise ValueError(f"ensemble_moments: next_input is {tuple(next_input.shape)} {next_input.dtype} with "
                             f"strides {next_input.stride()}, expected ({n}, >= {d}) float32 on the CPU with unit "
                             "column stride")
        if input_loc is None or input_scale is None:
            raise ValueError("ensemble_moments: next_input needs input_loc and input_scale")
        input_loc, input_scale = _fp32(input_loc.reshape(d)), _fp32(input_scale.reshape(d))
        next_address, next_stride = next_input.data_ptr(), next_input.stride(0)
        in_loc_address, in_scale_address = input_loc.data_ptr(), input_scale.data_ptr()
    if out is None:
        mu, sigma = torch.empty(n, d), torch.empty(n, d)
    else:
        mu, sigma = out
        if any(t.shape != (n, d) or t.dtype != torch.float32 or not t.is_contiguous() for t in out):
            raise ValueError(f"ensemble_moments: out is {[tuple(t.shape) for t in out]}, expected two ({n}, {d}) "
                             "contiguous float32 tensors")
    picked = picked_logvar = None
    member_address = 0
    if member_index is not None:
        member_index = member_index.reshape(n).to(torch.int64).contiguous()
        lo, hi = torch.aminmax(member_index) if n else (0, 0)
        if not (0 <= int(lo) and int(hi) < L):  # the kernel reads the member's row: never out of bounds
            raise ValueError(f"ensemble_moments: member_index outside [0, {L})")
        member_address = member_index.data_ptr()
        if noise is None:
            picked = torch.empty(n, d)
            picked_logvar = torch.empty(n, d) if with_logvar else None
    bounds = (0, 0, 0)
    if logvar_bounds is not None and member_index is not None and with_logvar:
        lo, hi = (t.float().reshape(d) for t in logvar_bounds)
        if not bool((hi - lo).max() < MAX_LOGVAR_SPAN):
            raise ValueError(f"ensemble_moments: logvar_bounds span {float((hi - lo).max()):.4g}, expected "
                             f"< {MAX_LOGVAR_SPAN}")
        hi, std_scale, span = hi.contiguous(), (scale * (0.5 * lo).exp()).contiguous(), (hi - lo).exp().contiguous()
        bounds = (hi.data_ptr(), std_scale.data_ptr(), span.data_ptr())
        logvar_bounds = (hi, std_scale, span)
    arguments = (output.data_ptr(), output.stride(0), output.stride(1), _DTYPE_CODES[output.dtype], L, n, d,
                 d if with_logvar else -1, particles, state.data_ptr(), loc.data_ptr(), scale.data_ptr(),
                 member_address, mu.data_ptr(), sigma.data_ptr(), 0 if picked is None else picked.data_ptr(),
                 0 if picked_logvar is None else picked_logvar.data_ptr(), *bounds, eta_address, noise_address,
                 next_address, next_stride, in_loc_address, in_scale_address, torch.get_num_threads())
    # every tensor whose address the call reads, kept alive with it
    alive = (output, state, loc, scale, member_index, logvar_bounds, eta, noise, next_input, input_loc, input_scale)

    def call(alive=alive) -> None:
        with seen_by_profiler("torchrl_softae::ensemble_moments"):
            _moments.ensemble_moments(*arguments)

    return call, (mu, sigma, picked, picked_logvar)


def _fp32(t: torch.Tensor) -> torch.Tensor:
    """``t`` as a contiguous fp32 tensor, itself when it is one (no call per argument at every step)."""
    return t if t.dtype == torch.float32 and t.is_contiguous() else t.float().contiguous()
