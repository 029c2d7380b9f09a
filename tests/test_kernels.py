"""The compiled kernels against their torch twins: the SiLU, mu and sigma in one pass, the
whole-network AMX and FMA kernels, and deterministic and sampled rollouts."""
import copy
import pickle
import threading

import pytest
import torch

from torchrl_softae.modules import EnsembleWorldModel
from torchrl_softae.modules.engine import amx_network, fma_network, moments_kernel, silu_kernel
from torchrl_softae.modules.engine.rollouts import is_rollout_key


def _model(**kw):
    kw = {"num_cells": 32, "depth": 2, **kw}
    return EnsembleWorldModel(3, 2, **kw)


def _assert_forced_path_matches_bmm(model, path, x, tol, dtype=None):
    """The model forced onto ``path`` (hidden layers in ``dtype``) predicts the batched-matmul
    path's means within ``tol``; leaves the model on ``bmm``."""
    model.engine.inference_path = path
    mu = model.network(x, dtype=dtype)[0]
    model.engine.inference_path = "bmm"
    torch.testing.assert_close(mu, model.network(x, dtype=dtype)[0], rtol=tol, atol=tol)


def _torch_bf16_layers(model, x):
    """The network as torch's bf16 paths compute it: bf16 matmul inputs, fp32 accumulation, bias and
    SiLU, hidden activations rounded to bf16, the last layer in fp32."""
    h = x.to(torch.bfloat16)
    for i, layer in enumerate(model.layers):
        y = torch.einsum("nk,lkm->lnm" if h.dim() == 2 else "lnk,lkm->lnm", h.float(),
                         layer.weight.to(torch.bfloat16).float()) + layer.bias.float()
        h = torch.nn.functional.silu(y).to(torch.bfloat16) if i < len(model.layers) - 1 else y
    return h


def _assert_a_copy_runs_its_own_weights(kernel, packed, x, outputs=14):
    """A copy of packed weights (a deepcopy or pickle of the model carries them) computes with its
    own tensors, not with the original's addresses: the original is zeroed before it runs."""
    want = kernel.forward(x, packed, outputs)
    copied = copy.deepcopy(packed)
    for w, b in packed.layers:
        w.zero_(), b.zero_()
    torch.testing.assert_close(kernel.forward(x, copied, outputs), want, rtol=0, atol=0)
    assert not torch.equal(kernel.forward(x, packed, outputs), want)  # (the zeroed weights ran)


def test_amx_weights_are_packed_as_tiles_of_input_pairs():
    """The AMX kernel's layout (csrc/amx_network.c), checked element by element on any CPU: tile
    (nb, kb) of member l holds W[l, 32 kb + 2 r + t, 16 nb + j] at [r, 2 j + t]; the padding to
    multiples of 32 inputs and outputs is zeros, in the weight and the bias."""
    torch.manual_seed(0)
    w, b = torch.randn(2, 40, 50), torch.randn(2, 50)
    packed, bias = amx_network.pack_layer(w, b)
    assert packed.shape == (2, 4, 2, 16, 32) and packed.dtype == torch.bfloat16
    assert bias.shape == (2, 64) and bias.dtype == torch.float32
    for l, nb, kb, r, j, t in [(0, 0, 0, 0, 0, 0), (1, 2, 1, 3, 5, 1), (0, 3, 0, 15, 1, 1), (1, 1, 1, 3, 15, 0)]:
        assert packed[l, nb, kb, r, 2 * j + t] == w[l, 32 * kb + 2 * r + t, 16 * nb + j].to(torch.bfloat16)
    assert packed[:, :, 1, 4:].abs().sum() == 0  # inputs 40..63
    assert packed[:, 3, :, :, 4:].abs().sum() == 0  # outputs 50..63 (block 3 holds 48..63)
    torch.testing.assert_close(bias[:, :50], b)
    assert bias[:, 50:].abs().sum() == 0


@pytest.mark.skipif(not amx_network.available(), reason=f"the AMX network kernel does not run here: {amx_network.why_not()}")
def test_amx_network_computes_the_bf16_network_on_every_row_count():
    """The whole network in one AMX call against torch's bf16 layers (bf16 matmuls, fp32 bias and
    SiLU, activations rounded to bf16): within a few bf16 roundings of a hidden activation, on
    row counts around the kernel's 16- and 32-row tiles, one thread and two; the model takes it
    when forced, and refuses it in fp32 with one line naming what it needs."""
    torch.manual_seed(0)
    model = EnsembleWorldModel(7, 3, num_cells=64, depth=3).eval()  # 10 inputs, 14 outputs: padded
    threads = torch.get_num_threads()
    try:
        with torch.no_grad():
            for n, t in [(1, 1), (16, 2), (17, 2), (33, 1), (70, 2), (300, 2)]:
                torch.set_num_threads(t)
                x = torch.randn(n, 10)
                h = _torch_bf16_layers(model, x)
                out = model.engine._run_path("amx-network", x, torch.bfloat16, None)
                assert out.shape == (5, n, 14) and out.dtype == torch.float32
                torch.testing.assert_close(out, h, rtol=0.02, atol=0.02)
                means = model.engine._run_path("amx-network", x, torch.bfloat16, 7)  # the mean head alone
                torch.testing.assert_close(means, out[..., :7], rtol=0, atol=0)
    finally:
        torch.set_num_threads(threads)
    x = torch.randn(40, 10)
    with torch.no_grad():
        _assert_forced_path_matches_bmm(model, "amx-network", x, tol=0.05, dtype=torch.bfloat16)
        model.engine.inference_path = "amx-network"
        with pytest.raises(RuntimeError, match="'amx-network' runs bf16 with nn.SiLU on an AMX CPU: got torch.float32"):
            model.network(x)
        _assert_a_copy_runs_its_own_weights(amx_network, model.engine._packed_network("amx-network", torch.bfloat16, None), x)
    w, b = amx_network.pack_layer(torch.randn(5, 10, 32), torch.randn(5, 32))
    with pytest.raises(ValueError, match=r"layer 0 is \(5, 2, 1, 16, 32\) torch.float32 .* expected pack_layer's"):
        amx_network.PackedNetwork([(w.float(), b)], 10)  # the kernel reads raw addresses: never a wrong layout
    with pytest.raises(ValueError, match=r"x \(40, 9\) torch.float32 on cpu, expected \(N, 10\) float32"):
        amx_network.forward(x[:, :9], amx_network.PackedNetwork([(w, b)], 10), 32)


def test_fma_weights_are_packed_as_panels_of_32_outputs():
    """The FMA kernel's layout (csrc/fma_network.c), checked element by element on any CPU: panel
    p of member l holds W[l, k, 32 p + j] at [k, j]; outputs padded to multiples of 32 and extra
    input rows (a hidden layer taking the previous one's padded outputs) are zeros."""
    torch.manual_seed(0)
    w, b = torch.randn(2, 40, 50), torch.randn(2, 50)
    packed, bias = fma_network.pack_layer(w, b, inputs=64)
    assert packed.shape == (2, 2, 64, 32) and packed.dtype == torch.float32
    assert bias.shape == (2, 64) and bias.dtype == torch.float32
    for l, p, k, j in [(0, 0, 0, 0), (1, 1, 39, 17), (0, 1, 7, 0), (1, 0, 20, 31)]:
        assert packed[l, p, k, j] == w[l, k, 32 * p + j]
    assert packed[:, :, 40:].abs().sum() == 0  # input rows 40..63
    assert packed[:, 1, :, 18:].abs().sum() == 0  # outputs 50..63
    torch.testing.assert_close(bias[:, :50], b)
    assert bias[:, 50:].abs().sum() == 0
    with pytest.raises(ValueError, match="inputs=30, expected at least the weight's 40"):
        fma_network.pack_layer(w, b, inputs=30)
    # bf16: pairs of inputs side by side, [p, i, j, t] = W[2 i + t, 32 p + j]; 41 inputs -> 42
    w = torch.randn(2, 41, 50)
    packed, bias = fma_network.pack_layer(w, b, dtype=torch.bfloat16)
    assert packed.shape == (2, 2, 21, 32, 2) and packed.dtype == torch.bfloat16
    for l, p, i, j, t in [(0, 0, 0, 0, 0), (1, 1, 20, 17, 0), (0, 1, 7, 0, 1), (1, 0, 13, 31, 1)]:
        assert packed[l, p, i, j, t] == w[l, 2 * i + t, 32 * p + j].to(torch.bfloat16)
    assert packed[:, :, 20, :, 1].abs().sum() == 0  # input 41 (padding to pairs)
    assert packed[:, 1, :, 18:].abs().sum() == 0  # outputs 50..63
    with pytest.raises(ValueError, match="inputs=43, expected at least the weight's 41 and even"):
        fma_network.pack_layer(w, b, inputs=43, dtype=torch.bfloat16)


@pytest.mark.skipif(not fma_network.available(), reason=f"the FMA network kernel does not run here: {fma_network.why_not()}")
def test_fma_network_computes_the_fp32_network_on_every_row_count_and_instruction_set():
    """The whole network in one fp32 call against float64 layers, on row counts around the
    kernel's blocks (12 rows with AVX-512, 6 with AVX2) and hidden widths that need padding: within
    fp32 rounding; the same bits on every instruction set and thread count (every output element
    is the same FMA sequence); the model takes it when forced and refuses it in bf16 with one
    line naming what it needs."""
    torch.manual_seed(0)
    model = EnsembleWorldModel(7, 3, num_cells=50, depth=3).eval()  # hidden 50 -> 64, outputs 14 -> 32
    threads, isa = torch.get_num_threads(), fma_network.isa()
    try:
        with torch.no_grad():
            for n in (1, 6, 7, 12, 13, 25, 206):
                x = torch.randn(n, 10)
                h = x.double()
                for i, layer in enumerate(model.layers):
                    h = torch.einsum("nk,lkm->lnm" if h.dim() == 2 else "lnk,lkm->lnm", h, layer.weight.double())
                    h = h + layer.bias.double()
                    h = torch.nn.functional.silu(h) if i < len(model.layers) - 1 else h
                outs = []
                for name in fma_network.supported_isas():
                    fma_network.use_isa(name)
                    for t in (1, 2):
                        torch.set_num_threads(t)
                        outs.append(model.engine._run_path("fma-network", x, torch.float32, None))
                assert outs[0].shape == (5, n, 14) and outs[0].dtype == torch.float32
                torch.testing.assert_close(outs[0].double(), h, rtol=1e-5, atol=1e-5)
                for out in outs[1:]:
                    torch.testing.assert_close(out, outs[0], rtol=0, atol=0)
                means = model.engine._run_path("fma-network", x, torch.float32, 7)  # the mean head alone
                torch.testing.assert_close(means, outs[-1][..., :7], rtol=0, atol=0)
    finally:
        torch.set_num_threads(threads)
        fma_network.use_isa(isa)
    x = torch.randn(40, 10)
    with torch.no_grad():
        _assert_forced_path_matches_bmm(model, "fma-network", x, tol=1e-5)
        model.engine.inference_path = "fma-network"
        with pytest.raises(RuntimeError, match="'fma-network' runs fp32 .* or bf16 .* got torch.float16"):
            model.network(x, dtype=torch.float16)
        _assert_a_copy_runs_its_own_weights(fma_network, model.engine._packed_network("fma-network", torch.float32, None), x)
    w, b = fma_network.pack_layer(torch.randn(5, 10, 32), torch.randn(5, 32))
    with pytest.raises(ValueError, match=r"layer 0 is \(5, 1, 10, 32\) torch.bfloat16 .* expected pack_layer's"):
        fma_network.PackedNetwork([(w.bfloat16(), b)], 10)  # the kernel reads raw addresses: never a wrong layout
    with pytest.raises(ValueError, match="in_features 9, expected the first layer's 10"):
        fma_network.PackedNetwork([(w, b)], 9)
    with pytest.raises(ValueError, match=r"x \(40, 9\) torch.float32 on cpu, expected \(N, 10\) float32"):
        fma_network.forward(x[:, :9], fma_network.PackedNetwork([(w, b)], 10), 32)


@pytest.mark.skipif(not fma_network.available(torch.bfloat16),
                    reason=f"the FMA kernel's bf16 form does not run here: {fma_network.why_not(torch.bfloat16)}")
def test_fma_network_computes_the_bf16_network_on_every_row_count():
    """The bf16 form (VDPBF16PS) against torch's bf16 layers (bf16 matmul inputs, fp32 accumulation,
    bias and SiLU, activations rounded to bf16): within a few bf16 roundings, on row counts around
    its 12-row blocks, odd inputs (padded to pairs) and padded widths; the same bits on one thread and
    two; the model takes it in bf16 when forced; where the AMX kernel runs too, both agree."""
    torch.manual_seed(0)
    model = EnsembleWorldModel(6, 3, num_cells=50, depth=3).eval()  # 9 inputs -> 10, hidden 50 -> 64
    threads = torch.get_num_threads()
    try:
        with torch.no_grad():
            for n in (1, 11, 12, 13, 25, 206):
                x = torch.randn(n, 9)
                h = _torch_bf16_layers(model, x)
                outs = []
                for t in (1, 2):
                    torch.set_num_threads(t)
                    outs.append(model.engine._run_path("fma-network", x, torch.bfloat16, None))
                assert outs[0].shape == (5, n, 12) and outs[0].dtype == torch.float32
                torch.testing.assert_close(outs[0], h, rtol=0.02, atol=0.02)
                torch.testing.assert_close(outs[1], outs[0], rtol=0, atol=0)
                if amx_network.available():
                    torch.testing.assert_close(model.engine._run_path("amx-network", x, torch.bfloat16, None), outs[0],
                                               rtol=0.02, atol=0.02)
    finally:
        torch.set_num_threads(threads)
    x = torch.randn(40, 9)
    with torch.no_grad():
        _assert_forced_path_matches_bmm(model, "fma-network", x, tol=0.05, dtype=torch.bfloat16)
        _assert_a_copy_runs_its_own_weights(fma_network, model.engine._packed_network("fma-network", torch.bfloat16, None), x,
                                            6)


def _bf16_ulps(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """How many bf16 steps apart two bf16 tensors of one sign are, element by element."""
    return (a.view(torch.int16).int() - b.view(torch.int16).int()).abs()


@pytest.mark.skipif(not silu_kernel.available(), reason="the compiled SiLU was not built (no C compiler at install)")
def test_compiled_silu_matches_torch_in_fp32_and_bf16_on_every_layout():
    """The kernel on every instruction set this CPU has: fp32 within a few 1e-7 relative of
    torch's SiLU; bf16 torch's bits or one ulp away, in at most 1 % of these inputs (AVX-512
    computes bf16 results to 1e-4 relative; the others round the same fp32 value as torch's);
    NaN where torch's is NaN, tails shorter than a vector, several threads and a channels-last 4-D
    buffer (the convolution path's) included; tensors it cannot take fall back to torch's."""
    g = torch.Generator().manual_seed(0)
    x = torch.cat([torch.randn(40_000, generator=g) * 4, torch.linspace(-30, 30, 1001),
                   torch.tensor([0.0, -0.0, float("inf"), float("nan"), 1e-30, -1e-30])])
    ref = torch.nn.functional.silu(x)
    best = silu_kernel.isa()
    assert best == silu_kernel.supported_isas()[-1] and "portable" in silu_kernel.supported_isas()
    try:
        for isa in silu_kernel.supported_isas():
            silu_kernel.use_isa(isa)
            for n in (x.numel(), 17, 5):  # a long buffer over several threads' chunks, and short tails
                got = silu_kernel.silu_(x[:n].clone())
                torch.testing.assert_close(got, ref[:n], rtol=1e-6, atol=1e-30, equal_nan=True, msg=isa)
                xb = x[:n].bfloat16()
                ref_b, got_b = torch.nn.functional.silu(xb.float()).bfloat16(), silu_kernel.silu_(xb.clone())
                assert torch.equal(got_b.isnan(), ref_b.isnan()), isa
                ulps = _bf16_ulps(got_b, ref_b)[~ref_b.isnan()]
                assert ulps.max() <= 1 and (ulps > 0).float().mean() <= 0.01, (isa, ulps.float().mean())
                if not isa.startswith("avx512"):
                    assert ulps.max() == 0, isa
            img = x[:4096].reshape(1, 64, 64, 1).to(memory_format=torch.channels_last)
            torch.testing.assert_close(silu_kernel.silu_(img.clone()), torch.nn.functional.silu(img),
                                       rtol=1e-6, atol=1e-30, msg=isa)
    finally:
        silu_kernel.use_isa(best)
    strided = x[:200].clone()[::2]  # not one dense block: torch's SiLU
    assert torch.equal(silu_kernel.silu_(strided), torch.nn.functional.silu(x[:200][::2]))
    with pytest.raises(ValueError, match="'sse9' is not one of this CPU's"):
        silu_kernel.use_isa("sse9")


@pytest.mark.skipif(not silu_kernel.available(), reason="the compiled SiLU was not built (no C compiler at install)")
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_compiled_bias_silu_adds_each_groups_row_before_the_activation(dtype):
    """``bias_silu_(x, b)`` is ``silu(x + b)`` with group ``g``'s bias row on every row of
    ``x[g]`` (a 1-D bias on every row), on every instruction set, row lengths that are not a
    multiple of the vector width and blocks over several threads' chunks included; torch's ops
    where the kernel cannot run; a bias that fits no group count is refused."""
    g = torch.Generator().manual_seed(1)
    best = silu_kernel.isa()
    try:
        for isa in silu_kernel.supported_isas():
            silu_kernel.use_isa(isa)
            for groups, rows, cols in ((5, 206, 256), (3, 7, 19), (1, 600, 1280)):
                x = (torch.randn(groups, rows, cols, generator=g) * 3).to(dtype)
                bias = torch.randn(groups, 1, cols, generator=g)
                want = torch.nn.functional.silu(x.float() + bias)
                got = silu_kernel.bias_silu_(x.clone(), bias)
                if dtype == torch.float32:
                    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6, msg=isa)
                else:
                    want = want.bfloat16()
                    ulps = _bf16_ulps(got, want)
                    assert ulps.max() <= 1 and (ulps > 0).float().mean() <= 0.01, (isa, groups, rows, cols)
            flat, row = torch.randn(30, 40, generator=g).to(dtype), torch.randn(40, generator=g)
            torch.testing.assert_close(silu_kernel.bias_silu_(flat.clone(), row).float(),
                                       torch.nn.functional.silu(flat.float() + row).to(dtype).float(),
                                       rtol=1e-2 if dtype == torch.bfloat16 else 1e-6, atol=1e-6, msg=isa)
    finally:
        silu_kernel.use_isa(best)
    strided = torch.randn(4, 10, 8, generator=g)[:, ::2]  # not dense: torch's ops, in place, same values
    bias = torch.randn(4, 8, generator=g)
    want = torch.nn.functional.silu(strided + bias.unsqueeze(1))
    assert silu_kernel.bias_silu_(strided, bias) is strided
    torch.testing.assert_close(strided, want)
    with pytest.raises(ValueError, match=r"bias_silu_: bias \(3, 8\) torch.float32, expected fp32 with 8 values"):
        silu_kernel.bias_silu_(torch.zeros(4, 10, 8), torch.zeros(3, 8))


@pytest.mark.skipif(not moments_kernel.available(), reason="the moments kernel was not built or this CPU lacks AVX2")
@pytest.mark.parametrize("isa", ["avx2", "avx512"])
def test_fused_moments_match_the_torch_ops(monkeypatch, isa):
    """``predict_moments`` through the one-pass kernel (on each instruction set this CPU runs it
    on) and through torch ops: the same mu, sigma, sampled member's mean and aleatoric std to fp32
    rounding, in fp32 and bf16, on the convolution (strided output) and matmul (contiguous) paths,
    with and without trajectory sampling and the log-variance head, for a deterministic model too;
    the kernel's own results are bit-for-bit reproducible, also on 2 threads (rows split between
    them)."""
    if isa not in moments_kernel.supported_isas():
        pytest.skip(f"this CPU runs the moments kernel on {moments_kernel.supported_isas()}, not {isa}")
    best = moments_kernel.isa()
    assert best == moments_kernel.supported_isas()[-1]
    moments_kernel.use_isa(isa)
    try:
        _fused_moments_match_the_torch_ops(monkeypatch)
    finally:
        moments_kernel.use_isa(best)
    with pytest.raises(ValueError, match="'sse9' is not one of this CPU's"):
        moments_kernel.use_isa("sse9")


def _fused_moments_match_the_torch_ops(monkeypatch):
    calls = []
    kernel = moments_kernel.ensemble_moments
    monkeypatch.setattr(moments_kernel, "ensemble_moments", lambda *a, **k: (calls.append(1), kernel(*a, **k))[1])
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    for probabilistic in (True, False):
        model = EnsembleWorldModel(21, 4, num_cells=32, depth=2, probabilistic=probabilistic)  # 21: a masked tail
        obs = torch.randn(700, 21, generator=g) * 3
        model.fit_normalizers(obs, torch.rand(700, 4, generator=g), obs + torch.randn(700, 21, generator=g))
        model.eval()
        obs, act = torch.randn(6, 70, 21, generator=g), torch.rand(6, 70, 4, generator=g) * 2 - 1
        member = torch.randint(5, (6, 70), generator=g)
        with torch.no_grad():
            for dtype in (None, torch.bfloat16):
                for path in ("conv", "bmm"):
                    model.engine.inference_path = path
                    for with_ale, idx in ((False, None), (True, member), (False, member)):
                        model.engine.fused_moments, n_calls = True, len(calls)
                        fused = model.predict_moments(obs, act, with_ale, idx, dtype=dtype)
                        assert len(calls) == n_calls + 1  # the kernel ran
                        again = model.predict_moments(obs, act, with_ale, idx, dtype=dtype)
                        assert torch.equal(torch.stack([t for t in fused if t is not None]),
                                           torch.stack([t for t in again if t is not None]))
                        model.engine.fused_moments = False
                        ref = model.predict_moments(obs, act, with_ale, idx, dtype=dtype)
                        assert len(calls) == n_calls + 2
                        for got, want in zip(fused, ref):
                            assert (got is None) == (want is None)
                            if want is not None:
                                assert got.shape == (6, 70, 21)
                                torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
                        mu, sigma = ref[0], ref[1]
                        members, _ = model.predict_members(obs, act, False, dtype=dtype)
                        torch.testing.assert_close(mu, members.mean(0), rtol=1e-5, atol=1e-5)
                        torch.testing.assert_close(sigma, members.std(0), rtol=1e-4, atol=1e-5)
        model.engine.fused_moments, model.engine.inference_path = True, "auto"
    raw = torch.randn(5, 8, 6)
    with pytest.raises(ValueError, match=r"member_index outside \[0, 5\)"):
        kernel(raw, torch.zeros(8, 3), torch.zeros(3), torch.ones(3), 3, torch.full((8,), 5), with_logvar=True)
    # the aleatoric std in the kernel's pass, at log-variances far outside the bounds too (the
    # torch ops' soft bounds, then scale * exp(v / 2)): within fp32 rounding of the reference
    lo, hi = torch.tensor([-10.0, -3.0, -20.0]), torch.tensor([0.5, 2.0, 40.0])
    raw[..., 3:] = torch.tensor([-300.0, -40.0, -10.0, -1.0, 0.0, 0.4, 3.0, 300.0]).view(1, 8, 1)
    member, scale = torch.arange(8) % 5, torch.tensor([0.5, 2.0, 1.0])
    *_, ale = kernel(raw, torch.zeros(8, 3), torch.zeros(3), scale, 3, member, True, (lo, hi))
    v = raw[member, torch.arange(8), 3:].double()
    v = hi - torch.nn.functional.softplus(hi - v)
    want = scale * (0.5 * (lo + torch.nn.functional.softplus(v - lo))).exp()
    torch.testing.assert_close(ale, want.float(), rtol=2e-6, atol=0)
    with pytest.raises(ValueError, match="logvar_bounds span 90, expected < 80"):
        kernel(raw, torch.zeros(8, 3), torch.zeros(3), scale, 3, member, True, (lo, lo + 90))


def _rollout_model(g: torch.Generator):
    """A small trained-normalizer ensemble for the rollout tests (21 states: a masked tail in the
    moments), its fitting states, the whole-network paths, and the (dtype, path) cases that run
    here: each whole-network kernel in each dtype it runs in, and a torch path."""
    torch.manual_seed(0)
    model = EnsembleWorldModel(21, 4, num_cells=64, depth=2)
    obs = torch.randn(700, 21, generator=g) * 3
    model.fit_normalizers(obs, torch.rand(700, 4, generator=g), obs + torch.randn(700, 21, generator=g))
    model.eval()
    whole = ("amx-network", "fma-network")
    cases = [(dtype, path) for dtype in (None, torch.bfloat16) for path in (*whole, "bmm")
             if path in model.engine.available_inference_paths(dtype or torch.float32)]
    return model, obs, whole, cases


@pytest.mark.skipif(not moments_kernel.available(), reason="the moments kernel was not built or this CPU lacks AVX2")
def test_deterministic_rollout_matches_the_torch_ops():
    """A deterministic rollout (Mean-AE, and SoftAE's mu + sigma * eta) as prepared kernel calls,
    on each whole-network kernel that runs here in each dtype, gives step by step the same bits as
    predict_moments and addcmul on the same inference path (the next state normalized into the
    next input by the moments kernel, as the torch ops do it); a torch path runs the torch ops. A
    second rollout of the same shape reuses the buffers and calls with its own values; a parameter
    change rebuilds them."""
    g = torch.Generator().manual_seed(1)
    model, obs, whole, cases = _rollout_model(g)
    assert ("fma-network" in model.engine.available_inference_paths(torch.float32)) == fma_network.available(torch.float32)
    H, M = 4, 37

    def reference(s, acts, eta, model=model, dtype=None):
        out = []
        for h in range(H):
            mu, sigma, _, _ = model.predict_moments(s, acts[h], dtype=dtype)
            s = mu if eta is None else torch.addcmul(mu, sigma, eta[h])
            out.append((s, sigma))
        return out

    def rollout(s, acts, eta, model=model, dtype=None):
        r = model.engine.deterministic_rollout(s, model.normalized_actions(acts), eta, dtype=dtype)
        return r, [(nxt.clone(), sigma.clone()) for nxt, sigma in r]

    with torch.no_grad():
        for dtype, path in cases:
            model.engine.inference_path = path
            for with_eta in (False, True):
                layouts = []
                for attempt in range(2):
                    s0 = torch.randn(M, 21, generator=g) * 2
                    acts = torch.rand(H, M, 4, generator=g) * 2 - 1
                    eta = 2 * torch.rand(H, M, 21, generator=g) - 1 if with_eta else None
                    r, got = rollout(s0, acts, eta, dtype=dtype)
                    assert len(r) == H and (r._layout.compiled is not None) == (path in whole)
                    layouts.append(r._layout)
                    for (s, sigma), (s_ref, sigma_ref) in zip(got, reference(s0, acts, eta, dtype=dtype)):
                        assert torch.equal(s, s_ref) and torch.equal(sigma, sigma_ref), (dtype, path, with_eta)
                assert layouts[0] is layouts[1]  # the same shape: buffers and prepared calls reused
        model.engine.inference_path = whole[1] if fma_network.available() else "bmm"
        s0, acts = torch.randn(M, 21, generator=g), torch.rand(H, M, 4, generator=g) * 2 - 1
        before, _ = rollout(s0, acts, None)
        model.layers[0].weight.mul_(1.5)  # its version counter moves: new packed weights, new calls
        after, got = rollout(s0, acts, None)
        assert after._layout is not before._layout
        for (s, sigma), (s_ref, sigma_ref) in zip(got, reference(s0, acts, None)):
            assert torch.equal(s, s_ref) and torch.equal(sigma, sigma_ref)
        # a copy (deepcopy, pickle) prepares its own calls on its own buffers and weights
        for copy_of in (copy.deepcopy, lambda m: pickle.loads(pickle.dumps(m))):
            twin = copy_of(model)
            for change in (False, True):
                if change:
                    twin.layers[0].weight.mul_(0.5)
                s1, acts1 = torch.randn(M, 21, generator=g), torch.rand(H, M, 4, generator=g) * 2 - 1
                _, theirs = rollout(s1, acts1, None, twin)
                _, mine = rollout(s0, acts, None)
                for got, m, s_, a_ in ((theirs, twin, s1, acts1), (mine, model, s0, acts)):
                    for (s, sigma), (s_ref, sigma_ref) in zip(got, reference(s_, a_, None, m)):
                        assert torch.equal(s, s_ref) and torch.equal(sigma, sigma_ref)
        # two rollouts of one shape at a time (nested, threads) each get buffers of their own; the
        # first to finish frees its buffers for the next; a rollout runs once
        s1, acts1 = torch.randn(M, 21, generator=g), torch.rand(H, M, 4, generator=g) * 2 - 1
        first = model.engine.deterministic_rollout(s0, model.normalized_actions(acts))
        second = model.engine.deterministic_rollout(s1, model.normalized_actions(acts1))
        assert first._layout is not second._layout
        both = [(a[0].clone(), b[0].clone()) for a, b in zip(first, second)]  # their steps interleaved
        for (got_first, got_second), ref_first, ref_second in zip(both, reference(s0, acts, None),
                                                                 reference(s1, acts1, None)):
            assert torch.equal(got_first, ref_first[0]) and torch.equal(got_second, ref_second[0])
        with pytest.raises(RuntimeError, match="already run"):
            list(first)
        third = model.engine.deterministic_rollout(s0, model.normalized_actions(acts))
        assert third._layout in (first._layout, second._layout)
        # rollouts of one shape from two threads at once (the kernels release the GIL): each its
        # own buffers while it runs, the same results as one after another
        jobs = [(torch.randn(M, 21, generator=g), torch.rand(H, M, 4, generator=g) * 2 - 1) for _ in range(2)]
        want = [reference(s_, a_, None) for s_, a_ in jobs]
        results = {}

        def run(i):
            with torch.no_grad():
                results[i] = [rollout(*jobs[i], None)[1] for _ in range(5)]

        threads = [threading.Thread(target=run, args=(i,)) for i in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for i in range(2):
            for got in results[i]:
                assert all(torch.equal(a[0], b[0]) for a, b in zip(got, want[i]))
        # a model in symlog space runs the torch ops (the moments kernel works in the state's units)
        curved = EnsembleWorldModel(21, 4, num_cells=32, depth=2, symlog_observations=True)
        curved.fit_normalizers(obs, torch.rand(700, 4, generator=g), obs + torch.randn(700, 21, generator=g))
        curved.eval()
        eta = 2 * torch.rand(H, M, 21, generator=g) - 1
        r, got = rollout(s0, acts, eta, curved)
        assert r._layout.compiled is None
        for (s, sigma), (s_ref, sigma_ref) in zip(got, reference(s0, acts, eta, curved)):
            assert torch.equal(s, s_ref) and torch.equal(sigma, sigma_ref)
        with pytest.raises(ValueError, match=r"eta has shape \(4, 37, 20\), expected \(4, 37, 21\)"):
            model.engine.deterministic_rollout(s0, model.normalized_actions(acts), torch.zeros(H, M, 20))
        with pytest.raises(ValueError, match=r"observation has shape \(36, 21\), expected \(37, 21\)"):
            model.engine.deterministic_rollout(s0[1:], model.normalized_actions(acts))


@pytest.mark.skipif(not moments_kernel.available(), reason="the moments kernel was not built or this CPU lacks AVX2")
@pytest.mark.parametrize("isa", ["avx512", "avx2"])
def test_moments_kernel_shares_rows_between_particles_and_samples_the_member(isa):
    """With ``particles`` each source row serves that many output rows (a candidate's particles at
    the first step), and with ``noise`` the first output is the member's mean plus its aleatoric
    std times the noise: the torch ops on the repeated rows, to fp32 rounding."""
    if isa not in moments_kernel.supported_isas():
        pytest.skip(f"this CPU does not run the {isa} variant")
    g = torch.Generator().manual_seed(0)
    L, sources, P, d = 5, 7, 3, 19  # 19: a masked tail in both variants
    raw = torch.randn(L, sources, 2 * d, generator=g)
    state, loc, scale = torch.randn(sources, d, generator=g), torch.randn(d, generator=g), torch.rand(d, generator=g) + 0.5
    member = torch.randint(L, (sources * P,), generator=g)
    noise = torch.randn(sources * P, d, generator=g)
    lo, hi = torch.full((d,), -6.0), torch.full((d,), 1.0)
    best = moments_kernel.isa()
    moments_kernel.use_isa(isa)
    try:
        mu, sigma, picked, ale = moments_kernel.ensemble_moments(
            raw.repeat_interleave(P, 1), state.repeat_interleave(P, 0), loc, scale, d, member, True, (lo, hi))
        nxt, sigma_shared, none1, none2 = moments_kernel.ensemble_moments(
            raw, state, loc, scale, d, member, True, (lo, hi), noise=noise, particles=P)
        mean_only, _, _, _ = moments_kernel.ensemble_moments(raw, state, loc, scale, d, member, noise=noise,
                                                              particles=P)
    finally:
        moments_kernel.use_isa(best)
    assert none1 is None and none2 is None  # with noise the member's mean and std are not kept
    torch.testing.assert_close(sigma_shared, sigma, rtol=0, atol=0)
    torch.testing.assert_close(nxt, picked + ale * noise)
    torch.testing.assert_close(mean_only, picked, rtol=0, atol=0)  # no log-variance head: s' = m_l
    with pytest.raises(ValueError, match="noise needs member_index"):
        moments_kernel.ensemble_moments(raw, state, loc, scale, d, noise=noise, particles=P)
    with pytest.raises(ValueError, match="noise needs member_index"):
        moments_kernel.ensemble_moments(raw, state, loc, scale, d, member, True, noise=noise, particles=P)
    with pytest.raises(ValueError, match=r"noise has shape \(7, 19\), expected \(21, 19\)"):
        moments_kernel.ensemble_moments(raw, state, loc, scale, d, member, noise=noise[:7], particles=P)


@pytest.mark.skipif(not moments_kernel.available(), reason="the moments kernel was not built or this CPU lacks AVX2")
def test_sampled_rollout_matches_the_torch_ops():
    """A trajectory-sampling rollout (PETS-AE, each particle on its member, with and without the
    aleatoric noise) as prepared kernel calls on each whole-network kernel that runs here in each
    dtype, and as torch ops on a torch path: step by step what predict_moments on every particle's
    rows and addcmul with the same noise give (the network once for a candidate's particles at the
    first step); the noise is the generator's, one draw per step; a second rollout of the shape
    reuses the layout."""
    from torchrl_softae.modules.engine import normal_kernel

    g = torch.Generator().manual_seed(1)
    model, _, whole, cases = _rollout_model(g)
    H, M, P = 4, 13, 10

    def reference(s, acts, members, seed, with_noise, dtype=None):
        gen, out = torch.Generator().manual_seed(seed), []
        s, members = s.repeat_interleave(P, 0), members.reshape(-1)
        for h in range(H):
            _, sigma, picked, ale = model.predict_moments(s, acts[h].repeat_interleave(P, 0), with_noise, members,
                                                          dtype=dtype)
            s = picked if not with_noise else picked + ale * normal_kernel.randn(picked.shape, gen)
            out.append((s, sigma))
        return out

    with torch.no_grad():
        for dtype, path in cases:
            model.engine.inference_path = path
            for with_noise in (False, True):
                layouts = []
                for attempt in range(2):
                    s0, acts = torch.randn(M, 21, generator=g) * 2, torch.rand(H, M, 4, generator=g) * 2 - 1
                    members = (torch.arange(P) + torch.randint(5, (M, 1), generator=g)) % 5
                    r = model.engine.sampled_rollout(s0, model.normalized_actions(acts), members, with_noise,
                                                     torch.Generator().manual_seed(attempt), dtype=dtype)
                    assert len(r) == H and r.compiled == (path in whole), (dtype, path)
                    assert r.network_calls == [((M, 25), with_noise)] + [((M * P, 25), with_noise)] * (H - 1)
                    layouts.append(r._layout)
                    got = [(nxt.clone(), sigma.clone()) for nxt, sigma in r]
                    for (s, sigma), (s_ref, sigma_ref) in zip(got, reference(s0, acts, members, attempt, with_noise,
                                                                             dtype)):
                        torch.testing.assert_close(s, s_ref)
                        torch.testing.assert_close(sigma, sigma_ref)
                assert layouts[0] is layouts[1]
        # a copy (deepcopy, pickle) leaves the rollouts' layouts behind (their prepared calls read
        # this model's buffers) and prepares its own, with the same results
        model.engine.inference_path = whole[1] if fma_network.available() else "bmm"
        for copy_of in (copy.deepcopy, lambda m: pickle.loads(pickle.dumps(m))):
            twin = copy_of(model)
            assert any(is_rollout_key(k) for k in model.engine._inference_cache)
            assert not any(is_rollout_key(k) for k in twin.engine._inference_cache)
            s0, acts = torch.randn(M, 21, generator=g), torch.rand(H, M, 4, generator=g) * 2 - 1
            members = torch.randint(5, (M, P), generator=g)
            mine, theirs = (
                [(nxt.clone(), sigma.clone()) for nxt, sigma in
                 m.engine.sampled_rollout(s0, m.normalized_actions(acts), members, generator=torch.Generator().manual_seed(3))]
                for m in (model, twin))
            for (s, sigma), (s_twin, sigma_twin) in zip(mine, theirs):
                assert torch.equal(s, s_twin) and torch.equal(sigma, sigma_twin)
        with pytest.raises(ValueError, match=r"member_index is \(12, 10\) torch.int64, expected \(13, P\)"):
            model.engine.sampled_rollout(s0, model.normalized_actions(acts), members[1:])
        with pytest.raises(ValueError, match=r"member_index outside \[0, 5\)"):
            model.engine.sampled_rollout(s0, model.normalized_actions(acts), members + 1)


@pytest.mark.skipif(not (silu_kernel.available() and moments_kernel.available()),
                    reason="the compiled kernels were not built here (no compiler or no AVX2)")
def test_compiled_kernels_show_in_torch_profiler_tables():
    """The C kernels run outside torch's dispatcher; while a profiler records they appear under
    their own names (so a profile's shares are of the whole op time), and outside one the result
    is the same."""
    from torch.profiler import profile

    torch.manual_seed(0)
    model = EnsembleWorldModel(7, 3, num_cells=32, depth=2).eval()
    model.engine.inference_path = "conv-silu-kernel"
    obs, act = torch.randn(50, 7), torch.rand(50, 3) * 2 - 1
    with torch.no_grad():
        plain = model.predict_moments(obs, act)
        with profile() as prof:
            profiled = model.predict_moments(obs, act)
    names = {e.key for e in prof.key_averages()}
    assert {"torchrl_softae::silu_", "torchrl_softae::ensemble_moments"} <= names
    for a, b in zip(plain, profiled):
        assert (a is None and b is None) or torch.equal(a, b)
