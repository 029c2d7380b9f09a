import math

import pytest
import torch

from torchrl_softae.modules.engine import normal_kernel

pytestmark = pytest.mark.skipif(not normal_kernel.available(), reason="the normal kernel is not loaded (not built, or SOFTAE_KERNELS=0)")


def test_draws_are_standard_normal():
    """Mean, variance, the Kolmogorov-Smirnov distance to N(0, 1), the tails, and no correlation
    between neighbours or between the two values of a Box-Muller pair (positions j and j + 16 of
    a block of 32), on 400000 seeded draws (deterministic: the same numbers at every run)."""
    from scipy import stats

    z = normal_kernel.randn((400_000,), torch.Generator().manual_seed(0)).double()
    n = z.numel()
    assert abs(float(z.mean())) < 4 / math.sqrt(n)
    assert abs(float(z.std()) - 1) < 4 * math.sqrt(2 / n)
    assert stats.kstest(z.numpy(), "norm").pvalue > 1e-3
    for threshold, p in ((2.0, 0.0455003), (3.0, 0.0026998)):
        observed = float((z.abs() > threshold).double().mean())
        assert abs(observed - p) < 5 * math.sqrt(p * (1 - p) / n), (threshold, observed)
    assert float(z.abs().max()) <= math.sqrt(-2 * math.log(2.0**-24)) + 1e-5  # Box-Muller on 24-bit uniforms
    pairs = z.reshape(-1, 32)
    for a, b in ((z[:-1], z[1:]), (pairs[:, :16].reshape(-1), pairs[:, 16:].reshape(-1)),
                 (pairs[:, :16].reshape(-1).square(), pairs[:, 16:].reshape(-1).square())):
        assert abs(float(torch.corrcoef(torch.stack([a, b]))[0, 1])) < 4 / math.sqrt(a.numel())


def test_the_stream_is_seeded_and_the_same_on_every_instruction_set_and_thread_count():
    """A value depends on the generator's state and its index only: the same generator state gives
    the same bits on every instruction set the CPU runs the kernel on and on 1 or 2 threads (and
    for a prefix, the same first values); the generator advances by one draw per call, so
    consecutive calls differ."""
    best, threads = normal_kernel.isa(), torch.get_num_threads()
    draws = {}
    try:
        for isa in normal_kernel.supported_isas():
            normal_kernel.use_isa(isa)
            for t in (1, 2):
                torch.set_num_threads(t)
                draws[isa, t] = normal_kernel.randn((70_001,), torch.Generator().manual_seed(5))
    finally:
        normal_kernel.use_isa(best)
        torch.set_num_threads(threads)
    first = next(iter(draws.values()))
    assert all(torch.equal(d.view(torch.int32), first.view(torch.int32)) for d in draws.values())
    prefix = normal_kernel.randn((33,), torch.Generator().manual_seed(5))
    assert torch.equal(prefix, first[:33])
    g = torch.Generator().manual_seed(5)
    a, b = normal_kernel.randn((100,), g), normal_kernel.randn((100,), g)
    assert torch.equal(a, first[:100]) and not torch.allclose(a, b)
    reference = torch.Generator().manual_seed(5)
    torch.randint(0, 2**63 - 1, (), generator=reference)
    torch.randint(0, 2**63 - 1, (), generator=reference)
    assert torch.equal(g.get_state(), reference.get_state())  # one draw of the generator per call


def test_add_scaled_randn_is_x_plus_std_times_the_stream_and_falls_back_elsewhere():
    """``x + std * z`` in one pass with ``z`` the same stream :func:`randn` draws from the same
    generator state, ``std`` broadcast; a float64 ``x`` or a non-contiguous one is handled the
    usual way (torch's draws for float64)."""
    x, std = torch.randn(50, 7), torch.rand(7)
    z = normal_kernel.randn((50, 7), torch.Generator().manual_seed(3))
    got = normal_kernel.add_scaled_randn(x, std, torch.Generator().manual_seed(3))
    torch.testing.assert_close(got, x + std * z, rtol=1e-6, atol=1e-6)
    strided = torch.randn(7, 50).t()
    torch.testing.assert_close(normal_kernel.add_scaled_randn(strided, std, torch.Generator().manual_seed(3)),
                               strided + std * z, rtol=1e-6, atol=1e-6)
    x64 = x.double()
    assert not normal_kernel.applies(x64)
    want = x64 + std.double() * torch.randn(50, 7, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    torch.testing.assert_close(normal_kernel.add_scaled_randn(x64, std.double(), torch.Generator().manual_seed(3)), want)
    assert normal_kernel.randn((4,), torch.Generator().manual_seed(0), dtype=torch.float64).dtype == torch.float64
    # kernel=False (a model built with kernels="torch", or engine.kernel_noise off): torch.randn's stream
    assert torch.equal(normal_kernel.normal_(torch.empty(9), torch.Generator().manual_seed(1), kernel=False),
                       torch.randn(9, generator=torch.Generator().manual_seed(1)))
    torch.testing.assert_close(normal_kernel.add_scaled_randn(x, std, torch.Generator().manual_seed(1), kernel=False),
                               x + std * torch.randn(50, 7, generator=torch.Generator().manual_seed(1)))
