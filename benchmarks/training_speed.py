"""Model training per gradient step: EnsembleTrainer in fp32 and in bf16 (autocast), interleaved.

    python benchmarks/training_speed.py [--dims 58 12] [--steps 250] [--rounds 7] [--threads 1]
                                        [--out benchmarks/results/training_speed-KIND.json]

Runs as the ``softae`` commands run (:func:`torchrl_softae.keep_freed_memory`). The paper's schedule (Table S6: 5 x 4 x 256 ensemble, batch 64, lr 5e-5, fused Adam) on 6,000
transitions of the given (d_s, d_a) (default the soft arm's). Prints the CPU and its GEMM peaks
(one 2048 x 2048 GEMM per dtype, the best of MKL and oneDNN), then the two trainers' ``fit``
interleaved round by round: median and best ms per gradient step, the share of the dtype's peak
(the step's matmul FLOPs: forward, input gradients, weight gradients), the ratio, and what
``precision="auto"`` resolves to here. Then a profile of one ``fit`` per dtype: the share of its
wall-clock in each part the trainer labels (batch draw, forward and loss, backward, optimizer,
validation, normalizers). And the bound that explains the ratio: the step's GEMMs alone (torch's
batched matmuls at the step's shapes) plus the fused Adam step alone, per dtype.

``--stacked-seeds S`` (default 2; 0 skips it) times what training S seeds' ensembles as one
ensemble of S x L members in one process could save per seed: one fit of the stacked ensemble
against S fits of one ensemble, interleaved, on the same threads. It is an upper bound: stacking
for real would also need each seed's own log-variance bounds and minibatch order.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDict

sys.path.insert(0, str(Path(__file__).parent))
from planning_speed import best_peaks, cpu_description, cpu_kind, peaks  # noqa: E402

from torchrl_softae import keep_freed_memory  # noqa: E402
from torchrl_softae.modules import EnsembleWorldModel  # noqa: E402
from torchrl_softae.objectives import EnsembleLoss, EnsembleTrainer  # noqa: E402
from torchrl_softae.objectives.training import resolve_training_dtype  # noqa: E402

PRECISIONS = ("fp32", "bf16")
#: the parts of a fit, as EnsembleTrainer labels them (torch.profiler.record_function)
PARTS = ("batch", "forward", "backward", "optimizer", "validation", "normalizers")


def step_flops(model: EnsembleWorldModel, batch_size: int) -> int:
    """Matmul FLOPs of one gradient step: every layer's forward and weight gradient, and the input
    gradient of every layer but the first (the data needs none)."""
    total = 0
    for i, layer in enumerate(model.layers):
        per_pass = 2 * model.ensemble_size * batch_size * layer.in_features * layer.out_features
        total += per_pass * (2 if i == 0 else 3)
    return total


def make_data(n: int, d_s: int, d_a: int) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(n, d_s, generator=g)
    return TensorDict({"observation": obs, "action": torch.rand(n, d_a, generator=g) * 2 - 1,
                       ("next", "observation"): obs + 0.1 * torch.randn(n, d_s, generator=g)}, [n])


def profile_fit(trainer: EnsembleTrainer, data) -> dict:
    """Seconds of one ``fit`` in each labelled part, and its wall-clock."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        t0 = time.perf_counter()
        trainer.fit(data)
        wall = time.perf_counter() - t0
    seconds = {part: 0.0 for part in PARTS}
    for event in prof.key_averages():
        if event.key.startswith("softae.train."):
            seconds[event.key.rsplit(".", 1)[1]] += event.cpu_time_total / 1e6
    return {"wall_s": wall, "parts_s": seconds}


def parts_alone(model: EnsembleWorldModel, batch_size: int, repeats: int) -> dict:
    """Milliseconds of the step's GEMMs alone (one batched matmul per layer and pass, at the step's
    shapes, in each dtype) and of the fused Adam step alone: a lower bound on a step's time."""
    L = model.ensemble_size
    out = {}
    for name, dtype in (("fp32", torch.float32), ("bf16", torch.bfloat16)):
        calls = []
        for i, layer in enumerate(model.layers):
            x = torch.randn(L, batch_size, layer.in_features, dtype=dtype)
            w = torch.randn(L, layer.in_features, layer.out_features, dtype=dtype)
            dy = torch.randn(L, batch_size, layer.out_features, dtype=dtype)
            calls.append(lambda x=x, w=w: torch.bmm(x, w))  # forward
            calls.append(lambda x=x, dy=dy: torch.bmm(x.transpose(1, 2), dy))  # weight gradient
            if i:
                calls.append(lambda w=w, dy=dy: torch.bmm(dy, w.transpose(1, 2)))  # input gradient

        def gemms(calls=calls):
            for c in calls:
                c()

        out[f"gemms_{name}_ms"] = _median_ms(gemms, repeats)
    params = [p.detach().clone().requires_grad_() for p in model.parameters()]
    for p in params:
        p.grad = torch.randn_like(p)
    opt = torch.optim.Adam(params, lr=1e-6, fused=True)
    out["adam_ms"] = _median_ms(opt.step, repeats)
    return out


def _median_ms(fn, repeats: int, calls: int = 50) -> float:
    fn()
    rounds = []
    for _ in range(repeats):
        t = time.perf_counter()
        for _ in range(calls):
            fn()
        rounds.append(1e3 * (time.perf_counter() - t) / calls)
    return statistics.median(rounds)


def stacked_seeds(args, data) -> dict:
    """ms per seed per gradient step: S seeds' ensembles stacked into one of S x L members against
    one ensemble (run S times), per dtype, interleaved; the saving is the stacked speed-up."""
    S = args.stacked_seeds
    d_s, d_a = args.dims
    out = {}
    for name in PRECISIONS:
        one = EnsembleTrainer(EnsembleLoss(EnsembleWorldModel(d_s, d_a)), max_grad_steps=args.steps, precision=name)
        stack = EnsembleTrainer(EnsembleLoss(EnsembleWorldModel(d_s, d_a, ensemble_size=S * one.model.ensemble_size)),
                                max_grad_steps=args.steps, precision=name)
        for t in (one, stack):
            t.fit(data)
        times = {"one": [], "stacked": []}
        for _ in range(args.rounds):
            t0 = time.perf_counter()
            one.fit(data)
            times["one"].append(1e3 * (time.perf_counter() - t0) / args.steps)
            t0 = time.perf_counter()
            stack.fit(data)
            times["stacked"].append(1e3 * (time.perf_counter() - t0) / args.steps / S)
        out[name] = {k: {"median_ms": statistics.median(v), "best_ms": min(v)} for k, v in times.items()}
        out[name]["speedup_median"] = out[name]["one"]["median_ms"] / out[name]["stacked"]["median_ms"]
        print(f"{S} seeds stacked, {name}: {out[name]['stacked']['median_ms']:.2f} ms per seed per step against "
              f"{out[name]['one']['median_ms']:.2f} ms alone (median; {out[name]['speedup_median']:.2f}x per seed)")
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dims", type=int, nargs=2, default=[58, 12], metavar=("D_S", "D_A"))
    p.add_argument("--steps", type=int, default=250, help="gradient steps per fit")
    p.add_argument("--rounds", type=int, default=7, help="interleaved rounds (at least 5)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--stacked-seeds", type=int, default=2, help="seeds stacked into one ensemble (0: skip)")
    p.add_argument("--out", default=None, help="write the result JSON here")
    args = p.parse_args()
    for name, low in (("steps", 1), ("rounds", 5), ("threads", 1)):
        if getattr(args, name) < low:
            p.error(f"--{name} {getattr(args, name)}: expected an integer >= {low}")
    torch.set_num_threads(args.threads)
    keep_freed_memory()  # as the softae commands run: freed memory reused, not faulted in again
    d_s, d_a = args.dims
    data = make_data(6000, d_s, d_a)
    trainers = {}
    for name in PRECISIONS:
        torch.manual_seed(0)
        trainers[name] = EnsembleTrainer(EnsembleLoss(EnsembleWorldModel(d_s, d_a)), max_grad_steps=args.steps,
                                         precision=name)
    model = trainers["fp32"].model
    flops = step_flops(model, trainers["fp32"].batch_size)
    cpu = cpu_description()
    pk = peaks(precisions=PRECISIONS)
    print(f"CPU: {cpu}; torch {torch.__version__}, {args.threads} thread(s); (d_s, d_a) = ({d_s}, {d_a}); "
          f"{flops / 1e6:.0f} MFLOP of matmuls per gradient step")
    for t in trainers.values():  # warm-up
        t.fit(data)
    ms = {k: [] for k in trainers}
    for r in range(args.rounds):
        for k, t in trainers.items():
            t0 = time.perf_counter()
            report = t.fit(data)
            ms[k].append(1e3 * (time.perf_counter() - t0) / report.grad_steps)
        pk = peaks(precisions=PRECISIONS, so_far=pk)  # between rounds: interference only lowers a peak
    peak = best_peaks(pk)
    print("GEMM peaks (GFLOP/s, 2048^3, best of MKL and oneDNN): "
          + ", ".join(f"{k} {v:.0f}" for k, v in peak.items()))
    rows = {}
    for k, v in ms.items():
        rows[k] = {"median_ms": statistics.median(v), "best_ms": min(v),
                   "pct_of_peak": 100 * flops / (min(v) / 1e3) / (peak[k] * 1e9)}
        print(f"{k:>5}: median {rows[k]['median_ms']:.2f} ms per gradient step, best {rows[k]['best_ms']:.2f}; "
              f"{rows[k]['pct_of_peak']:.0f} % of the {k} peak at the best")
    ratio = {"median": rows["fp32"]["median_ms"] / rows["bf16"]["median_ms"],
             "best": rows["fp32"]["best_ms"] / rows["bf16"]["best_ms"]}
    auto = resolve_training_dtype("auto", model)
    print(f"bf16 is {ratio['median']:.2f}x faster than fp32 (median), {ratio['best']:.2f}x (best); "
          f"precision='auto' trains in {'bf16' if auto == torch.bfloat16 else 'fp32'} here")

    alone = parts_alone(model, trainers["fp32"].batch_size, args.rounds)
    floor = {k: alone[f"gemms_{k}_ms"] + alone["adam_ms"] for k in PRECISIONS}
    print(f"alone: the step's GEMMs {alone['gemms_fp32_ms']:.2f} ms fp32, {alone['gemms_bf16_ms']:.2f} ms bf16; "
          f"fused Adam {alone['adam_ms']:.2f} ms. A step of GEMMs and Adam only: {floor['fp32']:.2f} / "
          f"{floor['bf16']:.2f} ms, so bf16 over fp32 is at most {floor['fp32'] / floor['bf16']:.2f}x with fp32 "
          f"master weights and optimizer state, and {rows['fp32']['best_ms'] / floor['bf16']:.2f}x against "
          "today's fp32 step")

    stacked = stacked_seeds(args, data) if args.stacked_seeds > 1 else None

    profiles = {}
    for k, t in trainers.items():
        profiles[k] = profile_fit(t, data)
        wall = profiles[k]["wall_s"]
        parts = profiles[k]["parts_s"]
        shares = ", ".join(f"{part} {100 * s / wall:.0f} %" for part, s in parts.items())
        other = 100 * (1 - sum(parts.values()) / wall)
        print(f"profile of one {k} fit ({1e3 * wall:.0f} ms, {args.steps} steps): {shares}, other {other:.0f} %")
    if args.out:
        Path(args.out).write_text(json.dumps({
            "cpu": cpu, "kind": cpu_kind(cpu), "torch": torch.__version__, "threads": args.threads,
            "dims": [d_s, d_a], "steps": args.steps, "step_mflop": flops / 1e6, "peaks_gflops": peak,
            "ms_per_step": ms, "rows": rows, "bf16_speedup": ratio,
            "auto": "bf16" if auto == torch.bfloat16 else "fp32", "alone_ms": alone, "profiles": profiles,
            "stacked_seeds": stacked,
        }, indent=1))


if __name__ == "__main__":
    main()
