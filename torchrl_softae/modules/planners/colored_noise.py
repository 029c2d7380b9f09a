"""Power-law ("colored") Gaussian noise along time, as iCEM samples action sequences.

A noise with power spectral density ``S(f) ~ 1 / f^beta`` [colored-noise exponent beta]:
beta = 0 is white noise, beta = 2 Brownian-like; iCEM (Pinneri et al. 2020) uses beta in [0.25, 4]
so that sampled action sequences are smoother and explore further than white noise.
Algorithm of Timmer & Koenig (1995): random Fourier coefficients scaled by ``f^(-beta/2)``,
inverse real FFT, normalized to unit variance.
"""
from __future__ import annotations

import math

import torch

from torchrl_softae.modules import normal_kernel

__all__ = ["colored_noise"]


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
            come from :mod:`~torchrl_softae.modules.normal_kernel`, seeded from it.
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
    f = torch.fft.rfftfreq(T, dtype=torch.float64)  # a handful of frequencies: computed on the CPU
    f[0] = 1.0 / T  # lowest resolvable frequency instead of the DC singularity
    s = f.pow(-exponent / 2.0)
    # Expected std of the un-normalized series, to normalize to unit variance.
    w = s.clone()
    w[-1] *= (1 + (T % 2)) / 2.0
    sigma = 2.0 * math.sqrt(float(w[1:].square().sum())) / T
    n_f = f.shape[0]
    s = s.to(dtype=dtype, device=device)
    re = normal_kernel.randn((*shape[:-1], n_f), generator, dtype, device) * s
    im = normal_kernel.randn((*shape[:-1], n_f), generator, dtype, device) * s
    if T % 2 == 0:  # the Nyquist coefficient of a real signal is real
        im[..., -1] = 0.0
        re[..., -1] *= math.sqrt(2.0)
    im[..., 0] = 0.0  # and so is the DC coefficient
    re[..., 0] *= math.sqrt(2.0)
    y = torch.fft.irfft(torch.complex(re, im), n=T, dim=-1) / sigma
    return y.to(dtype)
