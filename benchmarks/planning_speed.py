"""Time per MPC action at the paper's iCEM settings, side by side with TorchRL's CEMPlanner.

    python benchmarks/planning_speed.py            # all env shapes, ~3 minutes on 2 cores
    python benchmarks/planning_speed.py --quick    # (58, 12) and SoPrA only

Every planner plans over the same paper-sized ensemble (L=5, 4x256, SiLU) with the exploration
reward. Equal model evaluations: 2000 rows per horizon step (200 samples x 10 particles for iCEM,
2000 candidates for CEMPlanner), 5 iterations, H=10 (H=5 for SoPrA). Rows:

  cem-torchrl      TorchRL CEMPlanner over EnsembleModelEnv("sample") + UncertaintyReward
  icem-fp32-full   ICEMPlanner, PETS-AE propagation, 10 particles, fp32          [target (a)]
  icem-fp32-matmul same, oneDNN off: the ensemble's batched-matmul path (MKL's fp32 GEMM)
  icem-loop-full   same, with a naive Python loop over ensemble members
  icem-bf16-full   same as icem-fp32-full with bf16 hidden layers (compute-bound)  [target (c)]
  icem-fp32-dedup  ICEMPlanner, SoftAE (optimistic, deterministic): 1 particle    [target (b)]
  icem-bf16-dedup  same with bf16 hidden layers                                   [target (e)]
  icem-deadline    SoftAE bf16 with a 50 ms wall-clock budget per action           [target (d)]

Results go to stdout (markdown) and benchmarks/results/planning_speed.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
import warnings
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv
from torchrl.modules import CEMPlanner

from torchrl_softae.envs import EnsembleModelEnv, HallucinatedControl, UncertaintyReward
from torchrl_softae.modules import EnsembleWorldModel, ICEMPlanner, fast_bf16_available

SHAPES = [  # (name, d_s, d_a, H)
    ("arm58", 58, 12, 10),
    ("fish15", 15, 4, 10),
    ("leg10", 10, 5, 10),
    ("sopra32", 32, 6, 10),
    ("sopra32-H5", 32, 6, 5),
]


class LoopEnsembleWorldModel(EnsembleWorldModel):
    """The naive baseline: members evaluated one after the other in a Python loop."""

    def network(self, x, with_logvar=True, bound_logvar=True):
        outs = []
        for l in range(self.ensemble_size):
            h = x if x.dim() == 2 else x[l]
            for i, layer in enumerate(self.layers):
                h = torch.addmm(layer.bias[l], h, layer.weight[l])
                if i < len(self.layers) - 1:
                    h = self.activation(h)
            outs.append(h)
        out = torch.stack(outs)
        mean, logvar = out.chunk(2, dim=-1)
        return mean, (self._bound_logvar(logvar) if bound_logvar else logvar)


def make_model(cls, d_s, d_a, seed=0):
    torch.manual_seed(seed)
    m = cls(d_s, d_a)
    obs = torch.randn(1000, d_s)
    m.fit_normalizers(obs, torch.rand(1000, d_a) * 2 - 1, obs + 0.1 * torch.randn(1000, d_s))
    return m.eval()


def time_action(planner, obs, repeats):
    planner(obs.clone())  # warm-up (allocations, bf16 weight cache)
    best = float("inf")
    for _ in range(repeats):
        if hasattr(planner, "reset"):
            planner.reset()
        t = time.perf_counter()
        planner(obs.clone())
        best = min(best, time.perf_counter() - t)
    return best


def _best_gflops(fn, n=2048):
    fn()
    best = float("inf")
    for _ in range(10):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return 2 * n**3 / best


def matmul_peak(n=2048):
    """The issue's reference: best of 10 ``a @ b`` (MKL on x86)."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    return _best_gflops(lambda: a @ b, n)


def onednn_peak(dtype, n=2048):
    """The same GEMM through oneDNN (a 1x1 convolution, the kernels the ensemble's inference path
    uses). On AMD CPUs MKL's fp32 GEMM takes an AVX2 path: this is the CPU's real fp32 peak."""
    a, b = torch.randn(n, n, dtype=dtype), torch.randn(n, n, dtype=dtype)
    x, w = a.t().reshape(1, n, n, 1), b.reshape(n, n, 1, 1).to(memory_format=torch.channels_last)
    return _best_gflops(lambda: torch.nn.functional.conv2d(x, w), n)


def flops_per_action(model, rows, H, iters):
    per_row = sum(2 * layer.in_features * layer.out_features for layer in model.layers) * model.ensemble_size
    return per_row * rows * H * iters


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="only the arm (58, 12) and SoPrA (32, 6, H=5)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "planning_speed.json"))
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    shapes = [s for s in SHAPES if not args.quick or s[0] in ("arm58", "sopra32-H5")]

    peak = matmul_peak()
    dnn32, dnn16 = onednn_peak(torch.float32), onednn_peak(torch.bfloat16)
    print(f"# planning_speed: torch {torch.__version__}, {args.threads} threads, {platform.processor() or platform.machine()}")
    print(f"fp32 matmul peak (best of 10 2048x2048 a @ b): {peak / 1e9:.0f} GFLOP/s; the same GEMM through oneDNN: "
          f"fp32 {dnn32 / 1e9:.0f}, bf16 {dnn16 / 1e9:.0f} GFLOP/s (bf16/fp32 {dnn16 / dnn32:.2f}x); "
          f"native bf16: {fast_bf16_available()}")
    P, K, I, N = 200, 20, 5, 10
    results = {"peak_gflops": peak / 1e9, "onednn_fp32_gflops": dnn32 / 1e9, "onednn_bf16_gflops": dnn16 / 1e9,
               "threads": args.threads, "bf16_native": fast_bf16_available(), "rows": []}
    print("\n| shape | H | planner | ms/action | vs CEMPlanner | % matmul peak | % oneDNN fp32 peak |")
    print("|---|---|---|---|---|---|---|")
    for name, d_s, d_a, H in shapes:
        model = make_model(EnsembleWorldModel, d_s, d_a)
        loop_model = make_model(LoopEnsembleWorldModel, d_s, d_a)
        obs = TensorDict({"observation": torch.randn(d_s)}, [])
        sample_env = TransformedEnv(EnsembleModelEnv(model, mode="sample"), UncertaintyReward())
        loop_env = TransformedEnv(EnsembleModelEnv(loop_model, mode="sample"), UncertaintyReward())
        opt_env = TransformedEnv(EnsembleModelEnv(model, mode="optimistic"), Compose(HallucinatedControl(2.0), UncertaintyReward()))
        icem = dict(planning_horizon=H, optim_steps=I, num_candidates=P, top_k=K, num_particles=N)
        planners = {
            "cem-torchrl": (CEMPlanner(sample_env, H, I, P * N, K), P * N),
            "icem-fp32-full": (ICEMPlanner(sample_env, **icem), None),
            "icem-fp32-matmul": (ICEMPlanner(sample_env, **icem), None),
            "icem-loop-full": (ICEMPlanner(loop_env, **icem), None),
            "icem-bf16-full": (ICEMPlanner(sample_env, precision="bf16", **icem), None),
            "icem-fp32-dedup": (ICEMPlanner(opt_env, **icem), None),
            "icem-bf16-dedup": (ICEMPlanner(opt_env, precision="bf16", **icem), None),
            "icem-deadline": (ICEMPlanner(opt_env, precision="bf16", time_budget=0.05, **icem), None),
        }
        base = None
        for key, (planner, rows) in planners.items():
            with warnings.catch_warnings():  # flags() warns about Intel-GPU TF32, irrelevant here
                warnings.simplefilter("ignore")
                # "-matmul": oneDNN off, the ensemble falls back to baddbmm (MKL on x86)
                with torch.backends.mkldnn.flags(enabled=not key.endswith("-matmul")):
                    t = time_action(planner, obs, args.repeats)
            if rows is None:
                # iCEM adds xi*K kept elites (and the mean) to its samples
                rows = (P + int(0.3 * K + 0.999)) * planner.effective_particles
            base = t if key == "cem-torchrl" else base
            iters = planner.last_info.get("iterations", I) if isinstance(planner, ICEMPlanner) else I
            flops = flops_per_action(model, rows, H, iters) / t
            row = dict(shape=name, d_s=d_s, d_a=d_a, H=H, planner=key, seconds=t, speedup_vs_cem=base / t,
                       fraction_of_fp32_peak=flops / peak, fraction_of_onednn_fp32_peak=flops / dnn32, iterations=iters)
            results["rows"].append(row)
            print(f"| {name} ({d_s},{d_a}) | {H} | {key} | {t * 1e3:.1f} | {base / t:.2f}x | {100 * flops / peak:.0f}% "
                  f"| {100 * flops / dnn32:.0f}% |", flush=True)
    # compact summary (as in the README): ms per action and speed-up over CEMPlanner
    order = ["cem-torchrl", "icem-fp32-full", "icem-fp32-matmul", "icem-loop-full", "icem-bf16-full",
             "icem-fp32-dedup", "icem-bf16-dedup", "icem-deadline"]
    print("\n| (d_s, d_a), H | " + " | ".join(order) + " |")
    print("|---" * (len(order) + 1) + "|")
    for name, d_s, d_a, H in shapes:
        rr = {r["planner"]: r for r in results["rows"] if r["shape"] == name}
        cells = [f"{rr[k]['seconds'] * 1e3:.0f} ms ({rr[k]['speedup_vs_cem']:.1f}x)" for k in order]
        print(f"| ({d_s}, {d_a}), H={H} | " + " | ".join(cells) + " |")
    for name, d_s, d_a, H in shapes:
        rr = {r["planner"]: r for r in results["rows"] if r["shape"] == name}
        print(f"{name}: bf16/fp32 full {rr['icem-fp32-full']['seconds'] / rr['icem-bf16-full']['seconds']:.2f}x, "
              f"bf16/fp32 dedup {rr['icem-fp32-dedup']['seconds'] / rr['icem-bf16-dedup']['seconds']:.2f}x, "
              f"bf16/fp32-matmul full {rr['icem-fp32-matmul']['seconds'] / rr['icem-bf16-full']['seconds']:.2f}x, "
              f"batched vs loop (fp32 full) {rr['icem-loop-full']['seconds'] / rr['icem-fp32-full']['seconds']:.2f}x")
    os.makedirs(Path(args.out).parent, exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
