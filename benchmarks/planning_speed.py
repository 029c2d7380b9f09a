"""Time per MPC action at the paper's iCEM settings, every contender run as its users run it.

    python benchmarks/planning_speed.py              # all env shapes
    python benchmarks/planning_speed.py --quick      # (58, 12) and SoPrA (32, 6, H=5) only

Same paper-sized ensemble (L=5, 4x256, SiLU), same budget for everyone: 5 iterations of 200
candidates (K=20), H=10 (H=5 for SoPrA), 2000 model rows per horizon step where particles are
used. Every planner is called under ``torch.no_grad()`` as an MPC user would (TorchRL's planners do
not disable autograd themselves: timed with autograd on they record a graph at every model call).
The contenders are interleaved (one action of each in turn, ``--repeats`` rounds, at least 5) and
reported as median and best, so a noisy machine cannot make one ratio out of one lucky call. Each
round takes them in a new order (seeded), and each timed action comes right after an untimed one
of the same contender, as consecutive actions of an MPC loop do: a plan right after another
contender's fp32 network work ran 8-10 % slower whichever planner it was (two identical SoftAE
one-particle bf16 planners, AMX Xeon: 23.1-24.5 ms right after an fp32 replay, 21.0-22.6 ms one
place later; each after an untimed action of its own, 20.7-20.9 ms in either place: ``python
benchmarks/studies/order_effect.py``, ``benchmarks/results/order_effect-amx.txt``). So in a fixed order
without it, SoftAE's plan, which followed the fp32 one-particle contender's replay, was measured
slow; in a shuffled order without it every contender was, by as much as its predecessors were
heavy.

  cem-torchrl       TorchRL CEMPlanner over EnsembleModelEnv("sample") + UncertaintyReward, 2000 candidates
  mbrl-icem         mbrl-lib's ICEMOptimizer + GaussianMLP (TS-inf), 200 x 10 particles   [when mbrl imports];
                    each particle runs through its own member only (no epistemic std, which the
                    exploration reward needs): a fifth of the FLOPs of the others' 10-particle rows
  icem-fp32-full    our ICEMPlanner, PETS-AE propagation, 10 particles, fp32
  icem-bf16-full    same with bf16 hidden layers
  icem-fp32-dedup   our ICEMPlanner, SoftAE (optimistic, deterministic): 1 particle
  icem-bf16-dedup   same with bf16 hidden layers
  icem-deadline     SoftAE bf16 with a 50 ms wall-clock budget per action (fp32 where bf16 is not native)
  ...@PATH          (--compare-paths) the four icem rows with the ensemble's inference path fixed
                    (each of model.engine.available_inference_paths(dtype)) instead of measured at first use
  ...@torch-moments (--compare-moments) the four icem rows with mu and sigma computed by torch ops
                    (model.engine.fused_moments = False) instead of the one-pass kernel
  ...@torch-randn   (--compare-noise) the four icem rows with the model's normal draws by torch.randn
                    (model.engine.kernel_noise = False) instead of the counter-based kernel
  ...@step-loop     (--compare-rollout) the four icem rows scored by stepping the TorchRL stack
                    (model.engine.rollouts = False) instead of
                    the model's deterministic (one particle) or sampled (ten) rollout, prepared
                    kernel calls

``--layer-costs`` also times the arm-sized network as the planner runs it, fp32 and bf16 (its
ratio bounds bf16/fp32 of a plan), and ONE hidden layer (L=5 members, 256 -> 256) at the planner's row counts
(206 = 200 candidates + 6 kept elites with one particle, 2060 with ten): the GEMM alone
(batched matmul), its SiLU alone (in place: torch's, and the compiled kernel where it was built),
and both in one oneDNN call (grouped convolution with the SiLU as a post-op), fp32 and bf16,
interleaved. Where the activation costs about as much as
the GEMM, no GEMM speed-up can make the layer much faster: "layer bf16/fp32" is the bound.

``--network-alone`` also times, in the same interleaved rounds, each main contender's network
calls and nothing else (``CEMPlanner`` and the four icem rows; the calls of one plan recorded, then
replayed with the same row counts, heads, dtype and inference path): what the plan would take if
everything but the network cost nothing. For our planners it also times the plan's scoring (its
``evaluate`` calls), which splits the rest of the plan into the planner's own work (sampling,
ranking, refitting) and the per-step work between the network calls. Its ratios are the bounds the
README argues from: a plan cannot beat ``CEMPlanner`` by more than ``CEMPlanner``'s time over its
own network calls, nor be faster in bf16 than its network calls are unless the work between them
shrinks in bf16 by more than the network does (in no run so far). And since the two planners share
the model, a faster network speeds ``CEMPlanner`` up too: with it at the GEMM peak for both, our
plan can be at most ``CEMPlanner``'s FLOPs at the peak plus its time outside its network calls over
our FLOPs at the peak faster (:func:`shared_model_bound`, printed after the table).

``--profile`` runs ``torch.profiler`` over three plans of each of the four icem rows at the arm's
shape and prints what their op time goes to: the network's layers, and the largest other ops in ms
per plan.

``--loop-overhead`` times one SoftAE candidate evaluation (``evaluate_action_sequences``, one
particle, the arm's shape) against the same with mu and sigma by torch ops, a hand-written loop of
the same arithmetic (torch ops, checked equal) and its network calls alone: what the horizon loop
costs beyond the model.

On a CPU without native bf16 (no AMX-BF16, no AVX512-BF16: an AMD EPYC with AVX2 only is one) the
bf16 contenders, peaks and columns are left out (:func:`timed_precisions`; ``--force-bf16`` keeps
them): torch emulates bf16 there far below fp32 and ``precision="auto"`` plans in fp32.

Prints the CPU (vendor, AVX-512, AVX512-BF16, AMX), the GEMM peaks of every path measured in the
same run (MKL ``a @ b`` and oneDNN 1x1 convolution, fp32 and bf16), and "% of peak" against the
best peak of the dtype each planner's hidden layers use (FLOPs as the inference path runs them: the
log-variance head only where propagation draws aleatoric noise). "At the peak" is the bound a
target has to fit in: the contender's ensemble FLOPs at that peak with nothing else to do, and
the ratio to ``CEMPlanner`` that time would give. Results: stdout and
benchmarks/results/planning_speed-KIND.json (KIND: amx, avx512-bf16 or no-bf16). mbrl-lib (its own pins are from 2021, hence
``--no-deps`` for it alone; hydra-core brings the omegaconf and antlr4 it needs):
``pip install --no-deps mbrl==0.2.0 && pip install hydra-core termcolor`` (:data:`MBRL_INSTALL`).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import platform
import random
import statistics
import time
import warnings
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv
from torchrl.modules import CEMPlanner

from torchrl_softae import keep_freed_memory
from torchrl_softae.envs import EnsembleModelEnv, HallucinatedControl, UncertaintyReward
from torchrl_softae.modules import EnsembleWorldModel, ICEMPlanner
from torchrl_softae.modules.ensemble import ensemble_std
from torchrl_softae.modules.engine import amx_network, fma_network, moments_kernel, normal_kernel, silu_kernel
from torchrl_softae.modules.engine.precision import (
    cpu_flags, cpu_info, cpu_name, fast_bf16_available, onednn_bf16_available, resolve_planning_dtype)

SHAPES = [  # (name, d_s, d_a, H)
    ("arm58", 58, 12, 10),
    ("fish15", 15, 4, 10),
    ("leg10", 10, 5, 10),
    ("sopra32", 32, 6, 10),
    ("sopra32-H5", 32, 6, 5),
]
P, K, I, N = 200, 20, 5, 10
#: how to install the mbrl-lib anchor (measured on 2026-12-02: ``--no-deps`` on hydra-core too took
#: omegaconf 2.4 and antlr4 4.13, and hydra's import failed)
MBRL_INSTALL = "pip install --no-deps mbrl==0.2.0 && pip install hydra-core termcolor"
KEPT = math.ceil(0.3 * K)  # iCEM adds xi * K kept elites to its P samples
#: our four main contenders: PETS-AE with all particles ("full") or SoftAE with one ("dedup"), fp32 or bf16
ICEM_ROWS = ("icem-fp32-full", "icem-bf16-full", "icem-fp32-dedup", "icem-bf16-dedup")
#: the contenders --network-alone replays (the targets' ratios are between these)
ALONE = ("cem-torchrl", *ICEM_ROWS)


#: ``--allocator`` choices: "kept" is how the softae commands run (torchrl_softae.allocator)
ALLOCATORS = ("kept", "default")


def allocator_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--allocator", choices=ALLOCATORS, default="kept",
                   help="kept (default, as the softae commands run): keep_freed_memory() for every contender; "
                        "default: glibc's malloc as it comes (benchmarks/studies/allocator_speed.py compares the two)")


def use_allocator(choice: str) -> str:
    """Applies ``--allocator`` to this process (every contender in it); returns what the record says."""
    if choice == "kept":
        return "kept freed memory" if keep_freed_memory() else "default (keep_freed_memory does not apply here)"
    return "default"


def bf16_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force-bf16", action="store_true",
                   help="time bf16 even where the CPU has no native bf16 (torch emulates it: a full run takes hours)")


def timed_precisions(force_bf16: bool = False) -> tuple[str, ...]:
    """The planner precisions a run times: bf16 only where the CPU runs it natively (AMX-BF16,
    AVX512-BF16: :func:`fast_bf16_available`, what ``precision="auto"`` asks) or when forced.
    Elsewhere torch emulates bf16 far below fp32 (an AMD EPYC with AVX2 only: 0.9 against 54
    GFLOP/s at 1024^3, a one-particle arm plan 17.8 s against 0.32 s), ``"auto"`` plans in fp32 and
    no bf16 target applies."""
    return ("fp32", "bf16") if force_bf16 or fast_bf16_available() else ("fp32",)


def check_precision(p: argparse.ArgumentParser, precision: str, force_bf16: bool) -> None:
    """One line and exit 2 for ``--precision bf16`` where bf16 is not timed (:func:`timed_precisions`)."""
    if precision == "bf16" and "bf16" not in timed_precisions(force_bf16):
        p.error("--precision bf16: this CPU has no native bf16 (AMX-BF16, AVX512-BF16), torch would emulate it "
                "far below fp32; expected --precision fp32 here (or --force-bf16 to time the emulation)")


def cpu_description() -> dict:
    flags, info = cpu_flags(), cpu_info()
    return {"cpu": cpu_name(info), "avx512f": "avx512f" in flags,
            "avx512_bf16": "avx512_bf16" in flags, "amx_bf16": "amx_bf16" in flags, "machine": platform.machine()}


def cpu_kind(cpu: dict) -> str:
    """What decides bf16 speed here: AMX tiles, AVX512-BF16 dot products, or neither."""
    return "amx" if cpu["amx_bf16"] else "avx512-bf16" if cpu["avx512_bf16"] else "no-bf16"


def make_model(d_s, d_a, seed=0, ensemble_size=5):
    torch.manual_seed(seed)
    m = EnsembleWorldModel(d_s, d_a, ensemble_size=ensemble_size)
    obs = torch.randn(1000, d_s)
    m.fit_normalizers(obs, torch.rand(1000, d_a) * 2 - 1, obs + 0.1 * torch.randn(1000, d_s))
    return m.eval()


def pets_env(model):
    """PETS-AE's model env as the planner sees it: trajectory sampling and the exploration reward."""
    return TransformedEnv(EnsembleModelEnv(model, mode="sample"), UncertaintyReward())


def icem_settings(H: int) -> dict:
    """The paper's iCEM budget (P candidates, K elites, I iterations, N particles) at horizon ``H``."""
    return dict(planning_horizon=H, optim_steps=I, num_candidates=P, top_k=K, num_particles=N)


def softae_env(model):
    """SoftAE's model env as the planner sees it: optimistic propagation, hallucinated control
    (beta = 2) and the exploration reward."""
    return TransformedEnv(EnsembleModelEnv(model, mode="optimistic"), Compose(HallucinatedControl(2.0), UncertaintyReward()))


def _best(fn, repeats=10):
    fn()
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def peaks(n=2048, repeats=10, so_far: dict | None = None, precisions=("fp32", "bf16")) -> dict:
    """GFLOP/s of one n x n GEMM through MKL (``a @ b``) and through oneDNN (1x1 convolution), the
    best of ``repeats`` calls each, or of those and ``so_far`` (a peak measured earlier in the run):
    on a shared host interference only ever lowers a peak, so a benchmark measures them again
    between its rounds and keeps the best (one run's start-up peaks were half the true ones).
    ``precisions``: the dtypes to measure (the run's :func:`timed_precisions`)."""
    out = dict(so_far or {})
    for dtype, name in ((torch.float32, "fp32"), (torch.bfloat16, "bf16")):
        if name not in precisions:
            continue
        a, b = torch.randn(n, n, dtype=dtype), torch.randn(n, n, dtype=dtype)
        x, w = a.t().reshape(1, n, n, 1), b.reshape(n, n, 1, 1).to(memory_format=torch.channels_last)
        for key, fn in ((f"matmul_{name}", lambda: a @ b),
                        (f"onednn_{name}", lambda: torch.nn.functional.conv2d(x, w))):
            out[key] = max(out.get(key, 0.0), 2 * n**3 / _best(fn, repeats) / 1e9)
    return out


def layer_costs(repeats: int, calls: int = 50, L: int = 5, h: int = 256,
                precisions=("fp32", "bf16")) -> list[dict]:
    """Median microseconds of one hidden layer's GEMM, its SiLU and the fused GEMM + SiLU, and of
    the whole arm-sized network (``network_output``, every layer as the planner runs it: the
    inference path measured at first use, the log-variance head with 10 particles, as PETS-AE
    needs it), per dtype in ``precisions`` and row count (``repeats`` interleaved rounds of
    ``calls`` calls each)."""
    F = torch.nn.functional
    rows_of = {"1 particle": P + KEPT, "10 particles": (P + KEPT) * N}
    model = make_model(58, 12)
    jobs = {}
    for label, n in rows_of.items():
        x_in = torch.randn(n, 70, generator=torch.Generator().manual_seed(0))
        for name in precisions:
            def network(dtype=resolve_planning_dtype(name), x_in=x_in, with_logvar=label == "10 particles"):
                model.network_output(x_in, with_logvar, dtype)
            jobs[(label, name, "network")] = network
        for name in precisions:
            dtype = resolve_planning_dtype(name) or torch.float32
            g = torch.Generator().manual_seed(0)
            x = torch.randn(L, n, h, generator=g).to(dtype)
            w = (torch.randn(L, h, h, generator=g) / h**0.5).to(dtype)
            y = torch.randn(L, n, h, generator=g).to(dtype)
            xc = torch.randn(n, L * h, generator=g).to(dtype).t().unsqueeze(0).unsqueeze(-1)  # (1, L*h, n, 1)
            wc = w.transpose(1, 2).reshape(L * h, h, 1, 1).contiguous().to(memory_format=torch.channels_last)
            bc = torch.zeros(L * h, dtype=dtype)
            jobs[(label, name, "gemm")] = lambda x=x, w=w: torch.bmm(x, w)
            jobs[(label, name, "silu")] = lambda y=y: F.silu(y, inplace=True)
            if silu_kernel.available():
                jobs[(label, name, "silukernel")] = lambda y=y: silu_kernel.silu_(y)
            if hasattr(torch.ops.mkldnn, "_convolution_pointwise") and (name == "fp32" or onednn_bf16_available()):
                jobs[(label, name, "fused")] = lambda xc=xc, wc=wc, bc=bc: torch.ops.mkldnn._convolution_pointwise(
                    xc, wc, bc, [0, 0], [1, 1], [1, 1], L, "swish", [], "")
    times = {k: [] for k in jobs}
    with torch.no_grad():
        for fn in jobs.values():
            fn()
        for _ in range(repeats):
            for key, fn in jobs.items():
                t = time.perf_counter()
                for _ in range(calls):
                    fn()
                times[key].append((time.perf_counter() - t) / calls)
    out = []
    for label, n in rows_of.items():
        row = {"rows": n, "particles": label}
        for name in precisions:
            for part in ("gemm", "silu", "silukernel", "fused", "network"):
                if (label, name, part) in times:
                    row[f"{name}_{part}_us"] = 1e6 * statistics.median(times[(label, name, part)])
        out.append(row)
    return out


def print_layer_costs(rows: list[dict]) -> None:
    """SiLU share and layer ratio with the fastest SiLU of each dtype (torch's or the kernel)."""
    parts = ("gemm", "silu", "silukernel", "fused")
    if "bf16_gemm_us" not in rows[0]:  # fp32 only (no native bf16 here)
        print("\n| one hidden layer (5 x 256 -> 256) | rows | fp32 GEMM / SiLU torch / SiLU kernel / fused [us] "
              "| SiLU share of an fp32 layer (fastest SiLU) | the whole network, (58, 12) [us] |")
        print("|---|---|---|---|---|")
        for r in rows:
            silu = min(r[k] for k in ("fp32_silu_us", "fp32_silukernel_us") if k in r)
            cols = " / ".join(f"{r[k]:.0f}" if (k := f"fp32_{p}_us") in r else "-" for p in parts)
            print(f"| {r['particles']} | {r['rows']} | {cols} | {100 * silu / (r['fp32_gemm_us'] + silu):.0f}% "
                  f"| {r['fp32_network_us']:.0f} |")
        return
    print("\n| one hidden layer (5 x 256 -> 256) | rows | fp32 GEMM / SiLU torch / SiLU kernel / fused [us] "
          "| bf16 GEMM / SiLU torch / SiLU kernel / fused [us] | SiLU share of a bf16 layer (fastest SiLU) "
          "| GEMM bf16/fp32 | layer bf16/fp32 (fastest SiLU each) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        def cols(name):
            return " / ".join(f"{r[k]:.0f}" if (k := f"{name}_{p}_us") in r else "-" for p in parts)

        def silu(name):
            return min(r[k] for k in (f"{name}_silu_us", f"{name}_silukernel_us") if k in r)
        g32, s32, g16, s16 = r["fp32_gemm_us"], silu("fp32"), r["bf16_gemm_us"], silu("bf16")
        print(f"| {r['particles']} | {r['rows']} | {cols('fp32')} | {cols('bf16')} | {100 * s16 / (g16 + s16):.0f}% "
              f"| {g32 / g16:.2f}x | {(g32 + s32) / (g16 + s16):.2f}x |")
    print("\n| the whole network, (58, 12) | rows | fp32 [us] | bf16 [us] | bf16/fp32 (a plan made only of its "
          "network calls) |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['particles']} | {r['rows']} | {r['fp32_network_us']:.0f} | {r['bf16_network_us']:.0f} "
              f"| {r['fp32_network_us'] / r['bf16_network_us']:.2f}x |")


def loop_overhead(repeats: int, d_s: int = 58, d_a: int = 12, H: int = 10,
                  precisions=("fp32", "bf16")) -> list[dict]:
    """Median milliseconds of one SoftAE candidate evaluation (``evaluate_action_sequences``, the
    ``HallucinatedControl`` + ``UncertaintyReward`` stack, one particle, P + kept elites rows, H
    steps) against the same with mu and sigma by torch ops, a hand-written loop of the same arithmetic
    and the H network calls alone, in each of ``precisions``, interleaved. The hand-written loop's
    returns must equal ours."""
    model = make_model(d_s, d_a)
    env = softae_env(model)
    base = env.base_env
    rows = P + KEPT
    g = torch.Generator().manual_seed(0)
    start = TensorDict({"observation": torch.randn(1, d_s, generator=g)}, [1])
    seqs = torch.rand(1, rows, H, d_a + d_s, generator=g) * 2 - 1
    x = torch.randn(rows, d_s + d_a, generator=g)
    inn, out_norm = model.input_normalizer, model.output_normalizer

    def ours(prec, fused_moments=True):
        def fn():
            model.engine.fused_moments = fused_moments
            try:
                return base.evaluate_action_sequences(start, seqs, num_particles=1, env=env, precision=prec)[0]
            finally:
                model.engine.fused_moments = True
        return fn

    def hand(dtype):
        def fn():
            s = start["observation"].expand(rows, d_s)
            ret = torch.zeros(rows)
            for h in range(H):
                a, eta = seqs[0, :, h, :d_a], 2.0 * seqs[0, :, h, d_a:]
                y, _ = model.network((torch.cat([s, a], -1) - inn.loc) / inn.scale, with_logvar=False, dtype=dtype)
                members = torch.addcmul(s + out_norm.loc, out_norm.scale, y)
                mu = members.mean(0)
                sigma = ensemble_std(members, mu)
                s = torch.addcmul(mu, sigma, eta)
                ret += sigma.square().sum(-1).sqrt()
            return ret
        return fn

    def network(dtype):
        def fn():
            for _ in range(H):
                model.network(x, with_logvar=False, dtype=dtype)
        return fn

    parts = ["ours", "hand", "network"] + (["ours_torch_moments"] if moments_kernel.available() else [])
    jobs = {}
    for name in precisions:
        dtype = resolve_planning_dtype(name)
        jobs[(name, "ours")], jobs[(name, "hand")], jobs[(name, "network")] = ours(name), hand(dtype), network(dtype)
        if "ours_torch_moments" in parts:  # mu and sigma by torch ops, as the hand-written loop computes them
            jobs[(name, "ours_torch_moments")] = ours(name, fused_moments=False)
    with torch.no_grad():
        for name in precisions:
            a, b = jobs[(name, "ours")](), jobs[(name, "hand")]()
            if not torch.allclose(a, b, rtol=1e-3, atol=1e-3):
                raise AssertionError(f"the hand-written {name} loop disagrees with evaluate_action_sequences")
        times = {k: [] for k in jobs}
        for _ in range(repeats):
            for key, fn in jobs.items():
                t = time.perf_counter()
                fn()
                times[key].append(time.perf_counter() - t)
    return [{"dtype": name, "rows": rows, "H": H,
             **{f"{part}_ms": 1e3 * statistics.median(times[(name, part)]) for part in parts}}
            for name in precisions]


#: the ops that run the network's layers on the inference paths (the rest is the work between them)
#: (``aten::mm`` + ``bias_silu_``: the first layer and the hidden layers of ``bmm-silu-kernel``;
#: ``amx_network``, ``fma_network``: the whole network of ``amx-network`` or ``fma-network`` in one call)
NETWORK_OPS = ("mkldnn::_convolution_pointwise", "aten::convolution", "aten::mkldnn_convolution",
               "aten::bmm", "aten::baddbmm", "aten::addmm", "aten::mm", "aten::silu_", "torchrl_softae::silu_",
               "torchrl_softae::bias_silu_", "torchrl_softae::amx_network", "torchrl_softae::fma_network")


def contender_precision(key: str) -> str:
    """The planning precision of an icem contender (its key names it)."""
    return "bf16" if "bf16" in key else "fp32"


def icem_contender(key: str, sample_env, opt_env, icem: dict) -> tuple:
    """``(planner, precision, None)`` for ``key``, one of :data:`ICEM_ROWS` or a variant of one
    (``...@PATH``): the sample env for "full" rows, SoftAE's for "dedup" ones, bf16 where the key says so."""
    precision = contender_precision(key)
    return ICEMPlanner(sample_env if "full" in key else opt_env, precision=precision, **icem), precision, None


def profile_plans(plans: int = 3, top: int = 6, d_s: int = 58, d_a: int = 12, H: int = 10,
                  keys=ICEM_ROWS) -> list[dict]:
    """``torch.profiler`` over ``plans`` plans of each icem row in ``keys``: the share of self CPU
    time in the network's layers (:data:`NETWORK_OPS`) and the ``top`` largest other ops, ms per plan;
    and the median of ``plans`` plans timed without the profiler right before, in the same process
    (op time is held against these, not against the rounds, which ran at other moments)."""
    from torch.profiler import profile

    model = make_model(d_s, d_a)
    sample_env, opt_env = pets_env(model), softae_env(model)
    obs = TensorDict({"observation": torch.randn(d_s)}, [])
    icem = icem_settings(H)
    out = []
    with torch.no_grad():
        for key in keys:
            planner, *_ = icem_contender(key, sample_env, opt_env, icem)
            planner(obs.clone())
            planner(obs.clone())
            wall = []
            for _ in range(plans):
                t = time.perf_counter()
                planner(obs.clone())
                wall.append(time.perf_counter() - t)
            with profile() as prof:
                for _ in range(plans):
                    planner(obs.clone())
            ops = {e.key: e.self_cpu_time_total / 1e3 / plans for e in prof.key_averages()}  # ms per plan
            total = sum(ops.values())
            network = sum(v for k, v in ops.items() if k in NETWORK_OPS)
            rest = sorted(((v, k) for k, v in ops.items() if k not in NETWORK_OPS), reverse=True)[:top]
            out.append({"planner": key, "plan_ms": 1e3 * statistics.median(wall), "op_ms_per_plan": total,
                        "network_ms_per_plan": network,
                        "top_other_ops_ms_per_plan": {k: v for v, k in rest}})
    return out


def print_profile(rows: list[dict]) -> None:
    print("\n| torch.profiler, (58, 12) H=10, ms per plan | plan, unprofiled | op time | network layers "
          "| largest other ops |")
    print("|---|---|---|---|---|")
    for r in rows:
        others = ", ".join(f"{k.split('::')[-1]} {v:.1f}" for k, v in r["top_other_ops_ms_per_plan"].items())
        print(f"| {r['planner']} | {r['plan_ms']:.0f} | {r['op_ms_per_plan']:.0f} | {r['network_ms_per_plan']:.0f} "
              f"({100 * r['network_ms_per_plan'] / r['op_ms_per_plan']:.0f} %) | {others} |")


def print_loop_overhead(rows: list[dict]) -> None:
    torch_moments = "ours_torch_moments_ms" in rows[0]
    print(f"\n| one SoftAE candidate evaluation (58, 12), {rows[0]['rows']} rows, H={rows[0]['H']} | ours [ms] "
          + ("| ours, mu and sigma by torch ops [ms] " if torch_moments else "")
          + "| hand-written loop [ms] | network calls alone [ms] | network share of ours |")
    print("|---|---|---|---|---|" + ("---|" if torch_moments else ""))
    for r in rows:
        print(f"| {r['dtype']} | {r['ours_ms']:.1f} | "
              + (f"{r['ours_torch_moments_ms']:.1f} | " if torch_moments else "")
              + f"{r['hand_ms']:.1f} | {r['network_ms']:.1f} | {100 * r['network_ms'] / r['ours_ms']:.0f}% |")


def print_network_alone(rows: list[dict]) -> None:
    """Each replayed contender's plan against its network calls alone, and the two bounds they give:
    over ``CEMPlanner`` (its plan / our network calls) and bf16 over fp32 (fp32 calls / bf16 calls)."""
    print("\n| shape | planner | plan [ms] | its network calls alone [ms] | network share | calls "
          "| in scoring (evaluate) [ms] | the planner's own work (plan - scoring) [ms] "
          "| between the network calls (scoring - network alone) [ms] "
          "| bound: vs CEMPlanner (CEMPlanner's plan / these calls) | bound: bf16/fp32 (fp32 calls / bf16 calls) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "network_alone_s" not in r:
            continue
        same = {q["planner"]: q for q in rows if q["shape"] == r["shape"]}
        cem = same["cem-torchrl"]["median_s"]
        vs_cem = f"{cem / r['network_alone_s']:.2f}x" if r["planner"] != "cem-torchrl" else ""
        bf16 = ""
        if r["planner"].startswith("icem-bf16"):
            fp32 = same[r["planner"].replace("bf16", "fp32")]
            bf16 = f"{fp32['network_alone_s'] / r['network_alone_s']:.2f}x"
        split = " | | "
        if "scoring_s" in r:
            split = (f"{1e3 * r['scoring_s']:.1f} | {1e3 * (r['median_s'] - r['scoring_s']):.1f} "
                     f"| {1e3 * (r['scoring_s'] - r['network_alone_s']):.1f}")
        print(f"| {r['shape']} | {r['planner']} | {1e3 * r['median_s']:.1f} | {1e3 * r['network_alone_s']:.1f} "
              f"| {100 * r['network_alone_s'] / r['median_s']:.0f}% | {r['network_calls']} | {split} | {vs_cem} | {bf16} |")


def shared_model_bound(cem: dict, ours: dict) -> float | None:
    """The most a plan of ours can be faster than ``CEMPlanner``'s when the model the two share runs
    at the GEMM peak for both: ``CEMPlanner``'s ensemble FLOPs at the peak plus its time outside its
    network calls (TorchRL's own work, which no change to the model touches), over our FLOPs at the
    peak. Rows of one run (``results["rows"]``); ``None`` where ``CEMPlanner``'s network calls were not
    replayed (``--network-alone``). Any speed-up of the shared model speeds ``CEMPlanner`` up too, so
    this, not our FLOPs at the peak against ``CEMPlanner`` as measured, is what bounds the ratio."""
    if "network_alone_s" not in cem:
        return None
    return (cem["seconds_at_peak"] + cem["median_s"] - cem["network_alone_s"]) / ours["seconds_at_peak"]


def flops_per_row(model, with_logvar: bool = True) -> int:
    """FLOPs of one ensemble row (every member's matmuls), as the inference path runs it: without
    the log-variance half of the output layer where propagation has no aleatoric noise."""
    sizes = [(layer.in_features, layer.out_features) for layer in model.layers]
    if model.probabilistic and not with_logvar:
        sizes[-1] = (sizes[-1][0], model.observation_dim)
    return sum(2 * i * o for i, o in sizes) * model.ensemble_size


def best_peaks(pk: dict) -> dict:
    """The best GEMM peak of each dtype among the paths :func:`peaks` measured, GFLOP/s."""
    return {name: max(pk[f"matmul_{name}"], pk[f"onednn_{name}"]) for name in ("fp32", "bf16") if f"matmul_{name}" in pk}


def flops_per_action(model, rows, H, iters, first_rows=None, with_logvar=True):
    """FLOPs of the ensemble in one action: ``rows`` model rows per horizon step, ``first_rows`` at
    the first step (where our planner runs a candidate's particles once: they share its state and
    action), ``iters`` iterations."""
    first_rows = rows if first_rows is None else first_rows
    return flops_per_row(model, with_logvar) * (first_rows + rows * (H - 1)) * iters


class RecordNetworkCalls:
    """Records the input shape and ``with_logvar`` of every network call inside the block: every
    ``model.network_output`` call, and the steps of a planning rollout where they run as prepared
    kernel calls, without it (``model.engine.deterministic_rollout`` and ``sampled_rollout``:
    their ``network_calls``). The instance's methods are wrapped for the block's duration, then the
    class's are back."""

    ROLLOUTS = ("deterministic_rollout", "sampled_rollout")

    def __init__(self, model):
        self.model, self.calls = model, []

    def __enter__(self):
        network_output = self.model.network_output

        def recorded(x, with_logvar=True, dtype=None):
            self.calls.append((tuple(x.shape), with_logvar))
            return network_output(x, with_logvar, dtype)

        def recording(make_rollout):
            def recorded_rollout(*args, **kwargs):
                steps = make_rollout(*args, **kwargs)
                if steps.compiled:  # else its steps call network_output
                    self.calls += steps.network_calls
                return steps
            return recorded_rollout

        self.model.network_output = recorded
        for name in self.ROLLOUTS:
            setattr(self.model.engine, name, recording(getattr(self.model.engine, name)))
        return self

    def __exit__(self, *exc):
        del self.model.network_output
        for name in self.ROLLOUTS:
            delattr(self.model.engine, name)

    def flops(self) -> int:
        """The ensemble FLOPs of the recorded calls (rows x every member's matmuls, the
        log-variance head where it was computed)."""
        return sum(shape[-2] * flops_per_row(self.model, with_logvar) for shape, with_logvar in self.calls)


class TimeScoring:
    """Seconds one of our planners spends scoring candidates (its ``evaluate``: the model env's
    ``evaluate_action_sequences``) inside the block; the rest of its plan is the planner's own work
    (sampling, clipping, ranking, refitting)."""

    def __init__(self, planner):
        self.planner, self.seconds = planner, 0.0

    def __enter__(self):
        evaluate = self.planner.evaluate

        def timed(*args, **kwargs):
            t = time.perf_counter()
            try:
                return evaluate(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - t

        self.planner.evaluate = timed
        return self

    def __exit__(self, *exc):
        del self.planner.evaluate


class NetworkCallsAlone:
    """Replays the calls a :class:`RecordNetworkCalls` recorded, and nothing else: the same row counts
    and heads, in ``precision`` (``"fp32"``, ``"bf16"``; ``"auto"`` as the model measures it), on
    fixed inputs, with whatever inference path the model is set to. Its time is what the plan that
    made the calls would take if nothing but its network cost anything."""

    def __init__(self, recorded: RecordNetworkCalls, precision: str):
        g = torch.Generator().manual_seed(0)
        self.recorded, self.model, self.calls = recorded, recorded.model, recorded.calls
        self.dtype = self.model.engine.auto_planning_dtype() if precision == "auto" else resolve_planning_dtype(precision)
        self.inputs = {shape: torch.randn(shape, generator=g) for shape, _ in self.calls}

    def __call__(self):
        for shape, with_logvar in self.calls:
            self.model.network_output(self.inputs[shape], with_logvar, self.dtype)


class MbrlIcem:
    """mbrl-lib's iCEM + GaussianMLP (TS-inf particles) on the same budget, as its users call it."""

    def __init__(self, d_s, d_a, H):
        import gymnasium as gym
        import mbrl.models
        import mbrl.planning
        import numpy as np

        class Spaces(gym.Env):
            observation_space = gym.spaces.Box(-np.inf, np.inf, (d_s,), dtype=np.float32)
            action_space = gym.spaces.Box(-1.0, 1.0, (d_a,), dtype=np.float32)

        net = mbrl.models.GaussianMLP(d_s + d_a, d_s, "cpu", num_layers=4, ensemble_size=5, hid_size=256,
                                      propagation_method="fixed_model",
                                      activation_fn_cfg={"_target_": "torch.nn.SiLU"})
        model = mbrl.models.OneDTransitionRewardModel(net, target_is_delta=True, normalize=False, learned_rewards=False)
        self.env = mbrl.models.ModelEnv(Spaces(), model, termination_fn=lambda a, o: torch.zeros(o.shape[0], 1, dtype=torch.bool),
                                        reward_fn=lambda a, o: -o.square().sum(-1, keepdim=True),
                                        generator=torch.Generator().manual_seed(0))
        self.opt = mbrl.planning.ICEMOptimizer(
            num_iterations=I, elite_ratio=K / P, population_size=P, population_decay_factor=1.0,
            colored_noise_exponent=0.25, lower_bound=[[-1.0] * d_a] * H, upper_bound=[[1.0] * d_a] * H,
            keep_elite_frac=0.3, alpha=0.1, device=torch.device("cpu"))
        self.obs = np.random.default_rng(0).normal(size=d_s).astype(np.float32)
        self.H, self.d_a = H, d_a
        self.effective_particles = N
        self.last_info = {"iterations": I}

    def __call__(self, td):
        def obj(seqs):
            return self.env.evaluate_action_sequences(seqs, initial_state=self.obs, num_particles=N)

        return self.opt.optimize(obj, x0=torch.zeros(self.H, self.d_a))


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="only the arm (58, 12) and SoPrA (32, 6, H=5)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--compare-paths", action="store_true",
                   help="also time the icem rows with each inference path fixed (every available one)")
    p.add_argument("--compare-noise", action="store_true",
                   help="also time the icem rows with every normal draw by torch.randn instead of the noise kernel")
    p.add_argument("--compare-moments", action="store_true",
                   help="also time the icem rows with mu and sigma by torch ops instead of the one-pass kernel")
    p.add_argument("--compare-rollout", action="store_true",
                   help="also time the icem rows scored by the per-step tensor loop instead of the model's "
                        "deterministic (one particle) or sampled (ten) rollout")
    p.add_argument("--layer-costs", action="store_true",
                   help="also time one hidden layer's GEMM, SiLU and fused GEMM + SiLU at the planner's row counts")
    p.add_argument("--network-alone", action="store_true",
                   help="also time each main contender's network calls alone, in the same rounds (the bounds)")
    p.add_argument("--profile", action="store_true",
                   help="also profile three plans of each icem row at the arm's shape (where op time goes)")
    p.add_argument("--loop-overhead", action="store_true",
                   help="also time one SoftAE candidate evaluation against a hand-written loop and the network alone")
    p.add_argument("--out", default=None,
                   help="default benchmarks/results/planning_speed-KIND.json, KIND = amx, avx512-bf16 or no-bf16: "
                        "the project's machines differ in CPU, and each kind keeps its own record")
    allocator_option(p)
    bf16_option(p)
    args = p.parse_args()
    allocator = use_allocator(args.allocator)
    precisions = timed_precisions(args.force_bf16)
    icem_rows = tuple(k for k in ICEM_ROWS if contender_precision(k) in precisions)
    repeats = max(args.repeats, 5)
    torch.set_num_threads(args.threads)
    # the draws as this process would make them (SOFTAE_KERNELS=0: torch.randn for every contender)
    kernel_noise = normal_kernel.available()
    shapes = [s for s in SHAPES if not args.quick or s[0] in ("arm58", "sopra32-H5")]
    cpu = cpu_description()
    out = Path(args.out) if args.out else Path(__file__).parent / "results" / f"planning_speed-{cpu_kind(cpu)}.json"
    pk = peaks(precisions=precisions)
    print(f"# planning_speed: torch {torch.__version__}, {args.threads} threads, {cpu['cpu']}; AVX-512 {cpu['avx512f']}, "
          f"AVX512-BF16 {cpu['avx512_bf16']}, AMX {cpu['amx_bf16']}; allocator: {allocator}")
    print(f"compiled SiLU kernel: {silu_kernel.isa() or 'not built (torch SiLU only)'}; one-pass moments kernel: "
          f"{moments_kernel.isa() or 'no (not built, or no AVX2: torch ops)'}; AMX network kernel: "
          f"{'yes' if amx_network.available() else 'no (' + amx_network.why_not() + ')'}; FMA network kernel: "
          f"{fma_network.isa() or 'no (' + fma_network.why_not() + ')'}; normal draws: "
          f"{'counter-based kernel, ' + normal_kernel.isa() if kernel_noise else 'torch.randn'}",
          flush=True)
    if "bf16" not in precisions:
        print("bf16 contenders skipped: this CPU has no native bf16 (AMX-BF16, AVX512-BF16); precision='auto' plans "
              "in fp32 here and no bf16 target applies (--force-bf16 times torch's emulation anyway)", flush=True)
    try:
        import mbrl  # noqa: F401

        have_mbrl = True
    except Exception as e:  # noqa: BLE001
        have_mbrl = False
        print(f"mbrl-lib anchor skipped: {type(e).__name__}: {e} ({MBRL_INSTALL})")
    results = {"cpu": cpu, "silu_kernel_isa": silu_kernel.isa(), "moments_kernel": moments_kernel.available(),
               "amx_network_kernel": amx_network.available(), "fma_network_kernel_isa": fma_network.isa(),
               "normal_kernel_isa": normal_kernel.isa() if kernel_noise else None,
               "moments_kernel_isa": moments_kernel.isa(),
               "threads": args.threads, "allocator": allocator, "precisions": list(precisions),
               "contender_order": "a new seeded shuffle every round",
               "repeats": repeats, "rows": []}
    timed = []  # per shape: what the table needs once every round (and every peak) is measured
    for name, d_s, d_a, H in shapes:
        print(f"timing {name}: {repeats} interleaved rounds", flush=True)
        model = make_model(d_s, d_a)
        obs = TensorDict({"observation": torch.randn(d_s)}, [])
        sample_env, opt_env = pets_env(model), softae_env(model)
        icem = icem_settings(H)
        planners = {"cem-torchrl": (CEMPlanner(sample_env, H, I, P * N, K), "fp32", P * N)}
        if have_mbrl:  # TS-inf in mbrl-lib runs each particle through its own member only: 1/L of the rows
            planners["mbrl-icem"] = (MbrlIcem(d_s, d_a, H), "fp32", P * N // model.ensemble_size)
        planners.update({key: icem_contender(key, sample_env, opt_env, icem) for key in icem_rows})
        fastest = precisions[-1]  # SoftAE as fast as this CPU plans it: bf16 where native
        planners["icem-deadline"] = (ICEMPlanner(opt_env, precision=fastest, time_budget=0.05, **icem), fastest, None)
        path_of = {}  # contender -> the inference path it runs with ("auto": measured at first use)
        if args.compare_paths:
            for key in icem_rows:
                hidden_dtype = resolve_planning_dtype(contender_precision(key)) or torch.float32
                for path in model.engine.available_inference_paths(hidden_dtype):  # the paths that run in its dtype here
                    planners[f"{key}@{path}"] = icem_contender(key, sample_env, opt_env, icem)
                    path_of[f"{key}@{path}"] = path
        torch_moments = set()  # contenders whose mu and sigma are torch ops (the kernel's baseline)
        if args.compare_moments and moments_kernel.available():
            for key in icem_rows:
                planners[f"{key}@torch-moments"] = icem_contender(key, sample_env, opt_env, icem)
                torch_moments.add(f"{key}@torch-moments")

        torch_randn = set()  # contenders whose normal draws are torch.randn's (the noise kernel's baseline)
        if args.compare_noise and kernel_noise:
            for key in icem_rows:
                planners[f"{key}@torch-randn"] = icem_contender(key, sample_env, opt_env, icem)
                torch_randn.add(f"{key}@torch-randn")

        step_loop = set()  # contenders scored by stepping the TorchRL stack (the rollouts' baseline)
        if args.compare_rollout:
            for key in icem_rows:
                planners[f"{key}@step-loop"] = icem_contender(key, sample_env, opt_env, icem)
                step_loop.add(f"{key}@step-loop")

        def configure(key):  # the model as this contender runs it
            model.engine.inference_path = path_of.get(key, "auto")
            model.engine.fused_moments = key not in torch_moments
            model.engine.kernel_noise = key not in torch_randn
            model.engine.rollouts = key not in step_loop

        alone = {}  # contender -> its plan's network calls, replayed alone (--network-alone)
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for key, (planner, dtype, _) in planners.items():
                configure(key)
                planner(obs.clone())  # warm-up (allocations, weight caches, path measurement)
                if args.network_alone and key in ALONE:
                    if hasattr(planner, "reset"):
                        planner.reset()
                    with RecordNetworkCalls(model) as rec:
                        planner(obs.clone())
                    alone[key] = NetworkCallsAlone(rec, dtype)
                    alone[key]()
            scored = [k for k in alone if isinstance(planners[k][0], ICEMPlanner)]
            times = {k: [] for k in [*planners, *(f"{k}:network" for k in alone), *(f"{k}:scoring" for k in scored)]}
            order, shuffler = list(planners), random.Random(0)
            for _ in range(repeats):  # interleaved: one action of each contender per round
                shuffler.shuffle(order)  # a new order each round: no contender always follows the same one
                for key in order:
                    planner = planners[key][0]
                    configure(key)
                    # one untimed action first: the timed one follows the same planner's own action, as
                    # in an MPC loop, not another contender's work (see the module's docstring)
                    resets = hasattr(planner, "reset")
                    if resets:
                        planner.reset()
                    planner(obs.clone())
                    if resets:
                        planner.reset()
                    with TimeScoring(planner) if key in scored else contextlib.nullcontext() as scoring:
                        t = time.perf_counter()
                        planner(obs.clone())
                        times[key].append(time.perf_counter() - t)
                    if scoring is not None:
                        times[f"{key}:scoring"].append(scoring.seconds)
                    if key in alone:  # right after its plan, in the same state of the machine
                        t = time.perf_counter()
                        alone[key]()
                        times[f"{key}:network"].append(time.perf_counter() - t)
                pk = peaks(repeats=2, so_far=pk, precisions=precisions)  # between rounds, so a noisy moment cannot set the peak
        model.engine.inference_path, model.engine.fused_moments = "auto", True
        model.engine.kernel_noise = model.engine.rollouts = True
        chosen = sorted({f"{'bf16' if k[0] == torch.bfloat16 else 'fp32'} rows<={k[1]}: {v}"
                         for k, v in model.engine._path_memo.items() if isinstance(v, str)})
        timed.append((name, d_s, d_a, H, model, sample_env, planners, times, chosen, alone))

    best_peak = best_peaks(pk)
    results["peaks_gflops"] = pk
    print("\nGEMM peaks (2048^3, best of the start and every round) [GFLOP/s]: "
          + ", ".join(f"{k} {v:.0f}" for k, v in pk.items()))
    print("\n| shape | planner | median ms | best ms | vs CEMPlanner (median) | % of peak (its dtype) "
          "| at the peak: time, vs CEMPlanner |")
    print("|---|---|---|---|---|---|---|")
    for name, d_s, d_a, H, model, sample_env, planners, times, chosen, alone in timed:
        print(f"<!-- {name}: inference paths measured at first use: {'; '.join(chosen)} -->")
        base = statistics.median(times["cem-torchrl"])
        for key, (planner, dtype, rows) in planners.items():
            med, best = statistics.median(times[key]), min(times[key])
            first_rows = rows
            if rows is None:  # ours: EnsembleModelEnv runs the particles' shared first step once
                first_rows, rows = P + KEPT, (P + KEPT) * planner.effective_particles
            iters = getattr(planner, "last_info", {}).get("iterations", I)  # CEMPlanner keeps no info
            # the log-variance head runs only where propagation draws aleatoric noise (PETS-AE's
            # env, and mbrl-lib's GaussianMLP, which always computes both heads)
            env = getattr(planner, "env", sample_env)
            with_logvar = getattr(getattr(env, "base_env", env), "aleatoric_noise", True)
            flops = flops_per_action(model, rows, H, iters, first_rows, with_logvar)
            frac = flops / best / (best_peak[dtype] * 1e9)
            # the fastest this computation could be: its ensemble FLOPs at the GEMM peak, nothing else
            at_peak = flops / (best_peak[dtype] * 1e9)
            row = dict(shape=name, d_s=d_s, d_a=d_a, H=H, planner=key, median_s=med, best_s=best, dtype=dtype,
                       rows=rows, first_step_rows=first_rows, gflop=flops / 1e9, with_logvar=with_logvar,
                       speedup_vs_cem_median=base / med, fraction_of_peak=frac, iterations=iters,
                       seconds_at_peak=at_peak, max_speedup_vs_cem=base / at_peak, times=times[key])
            if key in alone:  # its network calls alone, timed right after it in every round
                net = statistics.median(times[f"{key}:network"])
                recorded = alone[key].recorded.flops()
                if abs(recorded - flops) > 0.01 * flops:  # the FLOP count above must be what the plan ran
                    print(f"warning: {name} {key}: the plan's recorded network calls are {recorded / 1e9:.1f} "
                          f"GFLOP, the formula says {flops / 1e9:.1f}")
                row.update(network_alone_s=net, network_calls=len(alone[key].calls),
                           recorded_gflop=recorded / 1e9, times_network_alone=times[f"{key}:network"])
                if f"{key}:scoring" in times:  # the plan's time in its evaluate calls
                    row.update(scoring_s=statistics.median(times[f"{key}:scoring"]),
                               times_scoring=times[f"{key}:scoring"])
            results["rows"].append(row)
            print(f"| {name} ({d_s},{d_a}) H={H} | {key} | {med * 1e3:.1f} | {best * 1e3:.1f} | {base / med:.2f}x | "
                  f"{100 * frac:.0f}% ({dtype}) | {at_peak * 1e3:.0f} ms, {base / at_peak:.2f}x |", flush=True)
    for name, *_ in shapes:
        rr = {r["planner"]: r for r in results["rows"] if r["shape"] == name}
        bf16 = ""
        if "bf16" in precisions:
            bf16 = (f"bf16/fp32 full {rr['icem-fp32-full']['median_s'] / rr['icem-bf16-full']['median_s']:.2f}x, "
                    f"bf16/fp32 dedup {rr['icem-fp32-dedup']['median_s'] / rr['icem-bf16-dedup']['median_s']:.2f}x, ")
        shared = [shared_model_bound(rr["cem-torchrl"], rr[k]) for k in ("icem-fp32-full", "icem-fp32-dedup")]
        print(f"{name}: {bf16}full fp32 vs CEMPlanner {rr['icem-fp32-full']['speedup_vs_cem_median']:.2f}x, "
              f"dedup fp32 vs CEMPlanner {rr['icem-fp32-dedup']['speedup_vs_cem_median']:.2f}x "
              f"(at most {rr['icem-fp32-full']['max_speedup_vs_cem']:.2f}x and "
              f"{rr['icem-fp32-dedup']['max_speedup_vs_cem']:.2f}x with our FLOPs at the fp32 peak"
              + (f", {shared[0]:.2f}x and {shared[1]:.2f}x with the shared model at the peak for both"
                 if None not in shared else "")
              + (f"; bf16/fp32 at most {best_peak['bf16'] / best_peak['fp32']:.2f}x, the peaks' ratio)"
                 if "bf16" in best_peak else ")")
              + (f", full fp32 vs mbrl-lib {rr['mbrl-icem']['median_s'] / rr['icem-fp32-full']['median_s']:.2f}x"
                 if "mbrl-icem" in rr else ""))
    if args.network_alone:
        print_network_alone(results["rows"])
    if args.layer_costs:
        results["layer_costs"] = layer_costs(repeats, precisions=precisions)
        print_layer_costs(results["layer_costs"])
    if args.profile:
        results["profile"] = profile_plans(keys=icem_rows)
        print_profile(results["profile"])
    if args.loop_overhead:
        results["loop_overhead"] = loop_overhead(repeats * 3, precisions=precisions)
        print_loop_overhead(results["loop_overhead"])
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1))
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
