"""One network call in passes of rows against one pass, at the row counts planning makes: an idea
tried and not used (benchmarks/README.md, "Tried and not used").

    python benchmarks/studies/tile_rows_speed.py                      # freed memory kept, as softae runs
    python benchmarks/studies/tile_rows_speed.py --allocator default  # glibc's malloc as it comes

The question: a hidden layer's output at N rows is N x 5 x 256 values, 84 MiB in fp32 at the 16480
rows of 8 ten-particle plans as one batch; would running the network in passes of a few thousand
rows, each layer's input and output then in cache, be faster than one pass? Here the arm-sized
network (``network_output`` as the planner calls it, the inference path measured at first use)
is timed at the rows of one ten-particle plan step (2060), of 8 one-particle plans as one batch
(1648) and of 8 ten-particle plans (16480), in one pass and in passes of 512, 1024 and 2048 rows
(the rows split as equally as they divide, the outputs written into one buffer as a tiled
network would), interleaved, median and best of the rounds, with the GEMM peak of the same run.
bf16 where the CPU has it natively (as ``planning_speed.py`` decides). Results: stdout and
benchmarks/results/tile_rows_speed-KIND[-default-allocator].json (KIND: amx, avx512-bf16 or
no-bf16).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parents[1]))
from planning_speed import (  # noqa: E402
    allocator_option, best_peaks, cpu_description, cpu_kind, flops_per_row, make_model, peaks, timed_precisions,
    use_allocator)

from torchrl_softae.modules.engine import paths  # noqa: E402
from torchrl_softae.modules.engine.precision import resolve_planning_dtype  # noqa: E402

#: (label, rows, with the log-variance head): what planning and batched evaluation call
CALLS = (("1 ten-particle plan step", 2060, True), ("8 one-particle plans as one batch", 1648, False),
         ("8 ten-particle plans as one batch", 16480, True))
#: pass sizes timed besides one pass
PASSES = ("one pass", 512, 1024, 2048)


def in_passes(model, x: torch.Tensor, with_logvar: bool, rows: int, dtype=None) -> torch.Tensor:
    """``model.network_output(x)`` in passes of at most ``rows`` rows, into one ``(L, N, out)``
    buffer (as the conv path lays it out: a view of ``(N, L, out)``)."""
    parts = [model.network_output(chunk, with_logvar, dtype) for chunk in x.tensor_split(-(-x.shape[0] // rows))]
    out = torch.empty(x.shape[0], parts[0].shape[0], parts[0].shape[-1], dtype=parts[0].dtype).transpose(0, 1)
    start = 0
    for part in parts:
        out[:, start:start + part.shape[1]].copy_(part)
        start += part.shape[1]
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rounds", type=int, default=11)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", default=None,
                   help="default benchmarks/results/tile_rows_speed-KIND[-default-allocator].json")
    allocator_option(p)
    args = p.parse_args()
    if args.rounds < 3:
        p.error(f"--rounds {args.rounds}: expected at least 3 (median and best of interleaved rounds)")
    torch.set_num_threads(args.threads)
    allocator = use_allocator(args.allocator)
    cpu = cpu_description()
    suffix = "-default-allocator" if args.allocator == "default" else ""
    out = Path(args.out) if args.out else Path(__file__).parents[1] / "results" / f"tile_rows_speed-{cpu_kind(cpu)}{suffix}.json"
    precisions = timed_precisions()
    print(f"# tile_rows_speed: torch {torch.__version__}, {args.threads} threads, {cpu['cpu']}; "
          f"AVX-512 {cpu['avx512f']}, AVX512-BF16 {cpu['avx512_bf16']}, AMX {cpu['amx_bf16']}; allocator: {allocator}",
          flush=True)
    model = make_model(58, 12)
    jobs = {}
    for label, rows, with_logvar in CALLS:
        x = torch.randn(rows, 70, generator=torch.Generator().manual_seed(0))
        for name in precisions:
            for passes in PASSES:
                def call(x=x, with_logvar=with_logvar, dtype=resolve_planning_dtype(name), passes=passes):
                    if passes == "one pass":
                        model.network_output(x, with_logvar, dtype)
                    else:
                        in_passes(model, x, with_logvar, passes, dtype)
                jobs[(label, name, passes)] = call
    rows_of = {label: rows for label, rows, _ in CALLS}
    times = {key: [] for key in jobs}
    pk = peaks(precisions=precisions)
    with torch.no_grad():
        print("first calls (the inference path is measured once per row bucket) ...", flush=True)
        for fn in jobs.values():
            fn()
        for r in range(args.rounds):
            for key, fn in jobs.items():
                calls = 1 if rows_of[key[0]] > 10_000 else 5  # about 0.2-0.5 s per timing either way
                t = time.perf_counter()
                for _ in range(calls):
                    fn()
                times[key].append((time.perf_counter() - t) / calls)
            pk = peaks(precisions=precisions, so_far=pk, repeats=3)
            print(f"round {r + 1}/{args.rounds}", flush=True)
    peak = best_peaks(pk)
    rows_out = []
    print("\nGEMM peaks [GFLOP/s]: " + ", ".join(f"{k} {v:.0f}" for k, v in pk.items()))
    print("\n| call | rows | dtype | passes | median ms | best ms | one pass / this (median) | % of peak |")
    print("|---|---|---|---|---|---|---|---|")
    for label, rows, with_logvar in CALLS:
        for name in precisions:
            whole = statistics.median(times[(label, name, "one pass")])
            for passes in PASSES:
                t = times[(label, name, passes)]
                med, best = statistics.median(t), min(t)
                frac = flops_per_row(model, with_logvar) * rows / med / (peak[name] * 1e9)
                shown = passes if isinstance(passes, str) else f"of {passes} rows"
                print(f"| {label} | {rows} | {name} | {shown} | {1e3 * med:.1f} | {1e3 * best:.1f} | {whole / med:.2f}x "
                      f"| {100 * frac:.0f} % |")
                rows_out.append({"call": label, "rows": rows, "precision": name, "passes": passes,
                                 "median_s": med, "best_s": best, "times_s": t, "speedup_vs_one_pass": whole / med,
                                 "fraction_of_peak": frac})
    choices = {k: v for k, v in paths.choices().items() if "70x256" in k}
    print("\nchoices measured at first use:\n" + "\n".join(f"  {k}: {v}" for k, v in choices.items()))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"cpu": cpu, "torch": torch.__version__, "threads": args.threads, "allocator": allocator,
                               "rounds": args.rounds, "peaks_gflops": pk, "choices": choices, "rows": rows_out},
                              indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
