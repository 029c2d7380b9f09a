"""Power-law ("colored") Gaussian noise along time, as iCEM samples action sequences.

A noise with power spectral density ``S(f) ~ 1 / f^beta`` [colored-noise exponent beta]:
beta = 0 is white noise, beta = 2 Brownian-like; iCEM (Pinneri et al. 2020) uses beta in [0.25, 4]
so that sampled action sequences are smoother and explore further than white noise.
Algorithm of Timmer & Koenig (1995): random Fourier coefficients scaled by ``f^(-beta/2)``,
inverse real FFT, normalized to unit variance.

That is a fixed linear map of the ``2 n_f`` Gaussian coefficients (``n_f = T // 2 + 1``): for the
planners' horizons (``T <= MAX_BASIS_T``) it is applied as two small matmuls with its matrix, the
inverse FFT of each unit coefficient computed once per ``(beta, T)``, instead of a complex FFT per
call (faster at iCEM's sizes; ``benchmarks/README.md``), the same values to fp32 rounding
(``test_colored_noise_basis_matches_the_fft``).
"""
from __future__ import annotations

import functools
import math

import torch

from torchrl_softae.modules.engine import normal_kernel

__all__ = ["colored_noise", "MAX_BASIS_T"]

#: longest series made with the matrix (its cost grows as T^2, the FFT's as T log T)
MAX_BASIS_T = 256


def _spectrum(exponent: float, T: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """The coefficients' scales: ``(re_scale, im_scale, ...)`` float64 ``(n_f,)`` each, with the DC
    and Nyquist terms of a real signal (real, times sqrt(2)), and the unnormalized series' std."""
    f = torch.fft.rfftfreq(T, dtype=torch.float64)  # a handful of frequencies: computed on the CPU
    f[0] = 1.0 / T  # lowest resolvable frequency instead of the DC singularity
    s = f.pow(-exponent / 2.0)
    # Expected std of the un-normalized series, to normalize to unit variance.
    w = s.clone()
    w[-1] *= (1 + (T % 2)) / 2.0
    sigma = 2.0 * math.sqrt(float(w[1:].square().sum())) / T
    re, im = s.clone(), s.clone()
    re[0] *= math.sqrt(2.0)  # the DC coefficient of a real signal is real
    im[0] = 0.0
    if T % 2 == 0:  # and so is the Nyquist coefficient
        re[-1] *= math.sqrt(2.0)
        im[-1] = 0.0
    return re, im, f, sigma


@functools.lru_cache(maxsize=64)
def _basis(exponent: float, T: int, dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The series as a linear map of the raw Gaussian coefficients: ``(B_re, B_im)``, ``(n_f, T)``
    each, ``y = re @ B_re + im @ B_im`` (computed in float64, once per arguments)."""
    re, im, f, sigma = _spectrum(exponent, T)
    eye, zero = torch.eye(f.shape[0], dtype=torch.float64), torch.zeros(f.shape[0], f.shape[0], dtype=torch.float64)
    b_re = torch.fft.irfft(torch.complex(eye * re, zero), n=T, dim=-1) / sigma
    b_im = torch.fft.irfft(torch.complex(zero, eye * im), n=T, dim=-1) / sigma
    return b_re.to(dtype=dtype, device=device), b_im.to(dtype=dtype, device=device)


def _coefficients(shape, n_f: int, generator, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    """The raw Gaussian coefficients, real parts then imaginary parts (two draws, in this order)."""
    re = normal_kernel.randn((*shape[:-1], n_f), generator, dtype, device)
    im = normal_kernel.randn((*shape[:-1], n_f), generator, dtype, device)
    return re, im


def _by_basis(exponent, shape, generator, dtype, device) -> torch.Tensor:
    b_re, b_im = _basis(float(exponent), shape[-1], dtype, torch.device(device))
    re, im = _coefficients(shape, b_re.shape[0], generator, dtype, device)
    return torch.matmul(re, b_re).add_(torch.matmul(im, b_im))


def _by_fft(exponent, shape, generator, dtype, device) -> torch.Tensor:
    T = shape[-1]
    re_s, im_s, f, sigma = _spectrum(exponent, T)
    re, im = _coefficients(shape, f.shape[0], generator, dtype, device)
    re = re * re_s.to(dtype=dtype, device=device)
    im = im * im_s.to(dtype=dtype, device=device)
    return (torch.fft.irfft(torch.complex(re, im), n=T, dim=-1) / sigma).to(dtype)


def colored_noise(
    exponent: float,
    shape: tuple[int, ...],
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device=None,
) -> torch.Tensor:
    """Unit-variance power-law noise whose last dimension is time.

    Args:
        exponent (float): spectral exponent beta >= 0.
        shape: output shape ``(..., T)``; every leading index is an independent series.
        generator: torch generator for reproducibility (on ``device``); fp32 draws on the CPU
            come from :mod:`~torchrl_softae.modules.engine.normal_kernel`, seeded from it.
        device: where the noise is created; default the generator's device (CPU without one).

    Returns:
        Tensor of ``shape``.
    """
    if exponent < 0:
        raise ValueError(f"colored_noise: exponent={exponent!r}, expected >= 0")
    if device is None:
        device = generator.device if generator is not None else torch.device("cpu")
    T = shape[-1]
    if exponent == 0 or T == 1:
        return normal_kernel.randn(shape, generator, dtype, device)
    make = _by_basis if T <= MAX_BASIS_T else _by_fft
    return make(exponent, tuple(shape), generator, dtype, device)
