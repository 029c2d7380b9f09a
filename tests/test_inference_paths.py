"""How the ensemble runs at inference: measured and cached path choices, packed and cached
weights, fused activations; every path computes what the training path computes."""

import pytest
import torch
from tensordict import TensorDict

from torchrl_softae.modules import EnsembleWorldModel
from torchrl_softae.modules.engine import network as engine_network
from torchrl_softae.modules.engine import amx_network, fma_network, silu_kernel
from torchrl_softae.modules.engine.precision import onednn_bf16_available
from torchrl_softae.objectives import EnsembleLoss


def _model(**kw):
    kw = {"num_cells": 32, "depth": 2, **kw}
    return EnsembleWorldModel(3, 2, **kw)


def test_inference_path_is_measured_once_cached_on_disk_and_can_be_fixed(tmp_path, monkeypatch):
    import json

    from torchrl_softae.modules.engine import paths

    monkeypatch.setenv("TORCHRL_SOFTAE_CACHE", str(tmp_path))
    monkeypatch.setattr(paths, "_MEMORY", {})
    model = EnsembleWorldModel(6, 2, num_cells=32, depth=2).eval()
    x = torch.randn(300, 8)
    with torch.no_grad():
        first = model.engine._inference_path(x, torch.float32, None)
        assert first in paths.INFERENCE_PATHS
        stored = json.loads((tmp_path / "paths.json").read_text())
        assert list(stored.values()) == [first] and "rows 512" in next(iter(stored))
        (key, choice), = paths.choices().items()  # what a run records: the choice, without the machine
        assert choice == first and key.startswith("ensemble 5|") and "rows 512" in key
        monkeypatch.setattr(paths, "_MEMORY", {})  # a new process reads the disk: the same choice
        model.engine._path_memo.clear()
        assert model.engine._inference_path(torch.randn(400, 8), torch.float32, None) == first
        expected = ("conv", "conv-fused", "bmm") + (("conv-silu-kernel", "bmm-silu-kernel") if silu_kernel.available()
                                                    else ()) + (("amx-network",) if amx_network.available() else ()) \
            + (("fma-network",) if fma_network.available() else ())
        assert model.engine.available_inference_paths() == expected
        usable = model.engine.available_inference_paths(torch.float32)  # amx-network is bf16 only
        assert usable == tuple(p for p in expected if p != "amx-network")
        # fma-network computes bf16 where the CPU has AVX512-BF16
        assert ("fma-network" in model.engine.available_inference_paths(torch.bfloat16)) == fma_network.available(
            torch.bfloat16)
        for forced in usable:
            model.engine.inference_path = forced
            assert model.engine._inference_path(x, torch.float32, None) == forced
        model.engine.inference_path = "auto"
        outs = {}
        for path in usable:
            model.engine.inference_path = path
            outs[path] = model.network(model.input_normalizer.normalize(x))[0]
        for path in usable:  # the same function either way
            torch.testing.assert_close(outs[path], outs["bmm"], rtol=1e-4, atol=1e-5)
    relu = EnsembleWorldModel(6, 2, num_cells=32, depth=2, activation_class=torch.nn.ReLU).eval()
    relu.engine.inference_path = "conv-silu-kernel"
    with torch.no_grad(), pytest.raises(RuntimeError, match="'conv-silu-kernel' needs nn.SiLU"):
        relu.network(x)



def test_the_cache_key_tells_apart_machines_with_the_same_model_name():
    """Two virtual machines both named "AMD EPYC", one with AVX-512 and one with AVX2 only, rank
    the inference paths differently: a choice measured on one must not be read on the other, nor
    one measured before the compiled SiLU ran on this instruction set."""
    from torchrl_softae.modules.engine.paths import cpu_key
    from torchrl_softae.modules.engine.precision import parse_cpuinfo

    avx512 = ("processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: 17\n"
              "model name\t: AMD EPYC\nflags\t\t: fpu sse2 avx2 fma avx512f avx512bw avx512_bf16\n\n"
              "processor\t: 1\nmodel name\t: something else\n")
    avx2 = avx512.replace("model\t\t: 17", "model\t\t: 1").replace(" avx512f avx512bw avx512_bf16", "")
    avx512, avx2 = parse_cpuinfo(avx512), parse_cpuinfo(avx2)
    assert cpu_key(avx512, "avx512bf16") == "AMD EPYC|family 25 model 17|avx2+fma+avx512f+avx512bw+avx512_bf16|SiLU kernel avx512bf16"
    assert cpu_key(avx2, "avx2") == "AMD EPYC|family 25 model 1|avx2+fma|SiLU kernel avx2"
    assert cpu_key(avx2, "portable") != cpu_key(avx2, "avx2")
    if silu_kernel.available():  # a kernel of another revision is another kernel
        assert silu_kernel.cache_tag() == f"{silu_kernel.isa()} revision {silu_kernel._silu.REVISION}"
    assert cpu_key(parse_cpuinfo(""), None) == "unknown|family ? model ?|no listed ISA|SiLU kernel not built"


def test_arm_cpuinfo_features_are_read_as_flags():
    """aarch64's /proc/cpuinfo lists its flags as ``Features`` and names the CPU by implementer and
    part: BFloat16 (``bf16``) must be seen, and two ARM cores must not share a cache key."""
    from torchrl_softae.modules.engine.paths import cpu_key
    from torchrl_softae.modules.engine.precision import flags_of, parse_cpuinfo

    neoverse_v1 = parse_cpuinfo("processor\t: 0\nBogoMIPS\t: 2100.00\nFeatures\t: fp asimd sve bf16 i8mm\n"
                                "CPU implementer\t: 0x41\nCPU architecture: 8\nCPU part\t: 0xd40\n\n")
    neoverse_n1 = parse_cpuinfo("processor\t: 0\nFeatures\t: fp asimd\nCPU implementer\t: 0x41\nCPU part\t: 0xd0c\n")
    assert {"bf16", "sve"} <= flags_of(neoverse_v1) and "bf16" not in flags_of(neoverse_n1)
    assert cpu_key(neoverse_v1, None) == "ARM implementer 0x41 part 0xd40|family ? model ?|sve+bf16+i8mm|SiLU kernel not built"
    assert cpu_key(neoverse_n1, None) == "ARM implementer 0x41 part 0xd0c|family ? model ?|no listed ISA|SiLU kernel not built"


@pytest.mark.parametrize("activation", [torch.nn.SiLU, torch.nn.ReLU, torch.nn.Tanh, torch.nn.ELU])
def test_fused_activation_path_computes_what_the_training_path_computes(activation):
    """The oneDNN post-op fusion (SiLU as "swish", ...) is the same network as autograd's layers,
    in fp32 and, up to bf16 rounding, in bf16; an activation without a post-op runs unfused."""
    torch.manual_seed(0)
    model = EnsembleWorldModel(6, 2, num_cells=32, depth=3, activation_class=activation).eval()
    x = torch.randn(300, 8)
    ref = model.network(x)[0].detach()  # grad enabled: the training path
    model.engine.inference_path = "conv-fused"
    with torch.no_grad():
        torch.testing.assert_close(model.network(x)[0], ref, rtol=1e-4, atol=1e-5)
        bf16 = torch.bfloat16
        if not onednn_bf16_available():  # e.g. AVX2 only: oneDNN has no bf16 convolution to fuse into
            with pytest.raises(RuntimeError, match="needs oneDNN's bf16 convolution"):
                model.network(x, dtype=bf16)
            return
        assert (model.network(x, dtype=bf16)[0] - ref).abs().max() < 0.05 * ref.abs().max()


def test_without_onednn_bf16_the_conv_paths_run_bf16_unpacked_and_auto_never_fuses(monkeypatch):
    """Where oneDNN has no bf16 convolution (a CPU with AVX2 only: its fused and pre-packed ops
    raise for bf16), bf16 on the conv paths runs torch's plain convolution on unpacked weights, the
    measured choice never offers the fused path, and forcing it names what is missing."""
    monkeypatch.setattr(engine_network, "onednn_bf16_available", lambda: False)
    torch.manual_seed(0)
    model = EnsembleWorldModel(6, 2, num_cells=32, depth=3).eval()
    x = torch.randn(300, 8)
    ref = model.network(x)[0].detach()
    bf16 = torch.bfloat16
    with torch.no_grad():
        for path in ("conv", "bmm"):
            model.engine.inference_path = path
            assert (model.network(x, dtype=bf16)[0] - ref).abs().max() < 0.05 * ref.abs().max()
        bf16_conv = [key for key in model.engine._inference_cache if key[1:3] == ("conv", torch.bfloat16)]
        assert bf16_conv and all(key[4] is None for key in bf16_conv)  # (id, "conv", dtype, cols, rows packed for)
        model.engine.inference_path = "conv-fused"
        with pytest.raises(RuntimeError, match="'conv-fused' in torch.bfloat16 needs oneDNN's bf16 convolution"):
            model.network(x, dtype=bf16)
        model.engine.inference_path = "auto"
        chosen = []
        monkeypatch.setattr(engine_network.paths, "choose", lambda key, candidates: chosen.append(
            (key, sorted(candidates))) or "conv")
        model.network(x, dtype=bf16)
    (key, candidates), = chosen
    assert "conv-fused" not in candidates and "plain conv weights" in key


@pytest.mark.skipif(engine_network._PACK_CONV_WEIGHT is None, reason="this torch build has no oneDNN weight pre-packing")
def test_packed_conv_weights_match(monkeypatch):
    """Weights pre-packed into oneDNN's layout once give the plain-weight convolutions' results, in
    fp32 and bf16, fused or not, at row counts other than the one they were packed for (bit for
    bit where both run the same oneDNN op; the unfused plain path runs ``F.conv2d``, whose kernel
    for a single row rounds differently, and so does oneDNN's one-thread kernel for a single row on
    plain weights); an optimizer step re-packs them (no stale weights)."""
    torch.manual_seed(0)
    # one exact pack (200 rows), then buckets: 7, 1 and 300 rows run on weights packed for 8, 2, 512
    monkeypatch.setattr(engine_network, "_EXACT_PACKS", 1)
    model = EnsembleWorldModel(6, 2, num_cells=32, depth=3).eval()
    xs = [torch.randn(n, 8) for n in (200, 7, 1, 300)]
    # (bf16 packs only where oneDNN has bf16 convolutions: see the test above)
    for dtype in (None, torch.bfloat16) if onednn_bf16_available() else (None,):
        for path in ("conv", "conv-fused"):
            model.engine.inference_path = path
            with torch.no_grad():
                packed = [model.network(x, dtype=dtype)[0] for x in xs]
                assert model.engine._exact_pack_rows == {200}
                assert [model.engine._pack_rows(x.shape[0]) for x in xs] == [200, 8, 2, 512]
                with monkeypatch.context() as m:
                    m.setattr(engine_network, "_PACK_CONV_WEIGHT", None)
                    plain = [model.network(x, dtype=dtype)[0] for x in xs]
            for x, a, b in zip(xs, packed, plain):
                if path == "conv-fused" and not (len(x) == 1 and torch.get_num_threads() == 1):
                    assert torch.equal(a, b)
                else:
                    torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
    model.engine.inference_path = "conv-fused"
    with torch.no_grad():
        before = model.network(xs[0])[0]
        model.layers[1].weight.mul_(0.5)  # in place, as an optimizer step: the version counter moves
        after = model.network(xs[0])[0]
    model.engine.inference_path = "bmm"
    with torch.no_grad():
        torch.testing.assert_close(after, model.network(xs[0])[0], rtol=1e-4, atol=1e-5)
    assert not torch.allclose(before, after)


@pytest.mark.parametrize("path", ["conv-fused", "bmm", "amx-network", "fma-network"])
def test_cached_inference_weights_follow_fused_optimizer_steps_copies_and_moves(path):
    """A fused optimizer step updates the parameters without moving their version counters, and
    ``.to()`` swaps their storage: the cast/packed inference weights must follow both, also for a
    deep copy, or the model plans with its weights from before training."""
    import copy

    torch.manual_seed(0)
    obs, act = torch.randn(64, 3), torch.randn(64, 2)
    td = TensorDict({"observation": obs, "action": act, ("next", "observation"): obs + 1.0}, [64])

    dtype = torch.bfloat16 if path == "amx-network" else None  # amx-network is bf16 only

    def cached_and_fresh(m):
        with torch.no_grad():
            cached = m.predict_members(obs, act, dtype=dtype)[0]
            m.engine.clear_inference_cache()
            return cached, m.predict_members(obs, act, dtype=dtype)[0]

    if path == "amx-network" and not amx_network.available():
        pytest.skip(f"the AMX network kernel does not run here: {amx_network.why_not()}")
    if path == "fma-network" and not fma_network.available():
        pytest.skip(f"the FMA network kernel does not run here: {fma_network.why_not()}")
    model = _model().eval()
    model.engine.inference_path = path
    for m in (model, copy.deepcopy(model)):
        m.engine.inference_path = path
        start, _ = cached_and_fresh(m)  # fills the cache
        optimizer = torch.optim.Adam(m.parameters(), lr=1e-2, fused=True)
        for _ in range(3):
            optimizer.zero_grad()
            EnsembleLoss(m)(td)["loss_model"].backward()
            optimizer.step()
        cached, fresh = cached_and_fresh(m)
        assert (cached - start).abs().max() > 1e-3  # training moved the predictions
        torch.testing.assert_close(cached, fresh, rtol=0, atol=0)
    # storage swapped by .to() (here a round trip through float64): the cache must not serve the old one
    with torch.no_grad():
        model.predict_members(obs, act, dtype=dtype)
        model.to(torch.float64).to(torch.float32)
        for layer in model.layers:
            layer.weight.data.mul_(0.5)  # through .data: detected only by the storage, not the version
        model.to(torch.float64).to(torch.float32)
        cached, fresh = cached_and_fresh(model)
    torch.testing.assert_close(cached, fresh, rtol=0, atol=0)


def test_auto_precision_is_fp32_where_bf16_is_not_native(monkeypatch):
    from torchrl_softae.modules.engine import precision

    monkeypatch.setattr(precision, "fast_bf16_available", lambda: False)
    assert EnsembleWorldModel(3, 1, num_cells=8, depth=1).engine.auto_planning_dtype() is None
