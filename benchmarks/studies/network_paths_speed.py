"""One network call of the arm-sized ensemble on every inference path this machine runs, at the row
counts planning makes, interleaved: how far each path is from the GEMM peak before a plan adds its
own work (benchmarks/README.md, "The whole fp32 network in one call").

    python benchmarks/studies/network_paths_speed.py                 # fp32 and, where native, bf16
    python benchmarks/studies/network_paths_speed.py --rounds 30

The network is ``EnsembleWorldModel(58, 12)`` (5 x 4 x 256, SiLU) called as the planner calls it
(``network_output`` with the path fixed): 206 rows (one-particle planning, the mean head) and 2060
rows (ten particles, both heads). Every path of a dtype runs once per round, in turn, with the GEMM
peaks (2048^3 through MKL and oneDNN) measured in the same rounds. A path's turn is ``--calls``
calls in a row, timed per call (in a plan the network calls follow each other with the weights in
cache; a single call after another path's runs with cold caches). The table gives each path's best
and median microseconds per call and its best against the dtype's best peak. Results: stdout and
benchmarks/results/network_paths_speed-KIND.json (KIND: amx, avx512-bf16 or no-bf16).
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
    KEPT, N, P, allocator_option, best_peaks, cpu_description, cpu_kind, flops_per_row, make_model, peaks,
    timed_precisions, use_allocator)

from torchrl_softae.modules.engine import fma_network  # noqa: E402
from torchrl_softae.modules.engine.precision import resolve_planning_dtype  # noqa: E402

#: (label, rows, with the log-variance head): what one- and ten-particle planning call
CALLS = (("1 particle", P + KEPT, False), ("10 particles", (P + KEPT) * N, True))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rounds", type=int, default=15)
    p.add_argument("--calls", type=int, default=10, help="calls in a row per path and round (timed per call: a "
                   "plan's network calls follow each other with the weights in cache)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--force-bf16", action="store_true", help="time bf16 paths where the CPU emulates bf16, too")
    allocator_option(p)
    p.add_argument("--out", default=None, help="default benchmarks/results/network_paths_speed-KIND.json")
    args = p.parse_args()
    if min(args.rounds, args.calls, args.threads) < 1:
        p.error(f"--rounds {args.rounds}, --calls {args.calls} and --threads {args.threads}: expected at least 1 "
                "each")
    allocator = use_allocator(args.allocator)
    torch.set_num_threads(args.threads)
    cpu = cpu_description()
    precisions = timed_precisions(args.force_bf16)
    print(f"# network_paths_speed: torch {torch.__version__}, {args.threads} threads, {cpu['cpu']}; AVX-512 "
          f"{cpu['avx512f']}, AVX512-BF16 {cpu['avx512_bf16']}, AMX {cpu['amx_bf16']}; FMA network kernel: "
          f"{fma_network.isa() or 'no'}; allocator: {allocator}; {args.rounds} interleaved rounds of {args.calls} "
          "calls per path", flush=True)
    model = make_model(58, 12)
    jobs = {}
    for label, rows, with_logvar in CALLS:
        x = torch.randn(rows, 70, generator=torch.Generator().manual_seed(0))
        for name in precisions:
            dtype = resolve_planning_dtype(name) or torch.float32
            for path in model.engine.available_inference_paths(dtype):
                def call(path=path, dtype=dtype, x=x, with_logvar=with_logvar):
                    model.engine.inference_path = path
                    for _ in range(args.calls):
                        model.network_output(x, with_logvar, dtype)
                jobs[(label, name, path)] = call
    times = {key: [] for key in jobs}
    pk = {}
    with torch.no_grad():
        for fn in jobs.values():  # warm-up: packed weights, first-touch allocations
            fn()
        for _ in range(args.rounds):
            pk = peaks(repeats=2, so_far=pk, precisions=precisions)
            for key, fn in jobs.items():
                t = time.perf_counter()
                fn()
                times[key].append((time.perf_counter() - t) / args.calls)
    model.engine.inference_path = "auto"
    best = best_peaks(pk)
    print(f"GEMM peaks (2048^3, best of every round) [GFLOP/s]: "
          + ", ".join(f"{k} {v:.0f}" for k, v in sorted(pk.items())))
    print("\n| call | rows | dtype | path | best [us] | median [us] | % of the dtype's peak (best) |")
    print("|---|---|---|---|---|---|---|")
    rows_out = []
    for (label, name, path), ts in times.items():
        rows, with_logvar = next((r, w) for lab, r, w in CALLS if lab == label)
        flops = flops_per_row(model, with_logvar) * rows
        row = {"call": label, "rows": rows, "dtype": name, "path": path, "best_us": 1e6 * min(ts),
               "median_us": 1e6 * statistics.median(ts), "fraction_of_peak": flops / min(ts) / 1e9 / best[name],
               "times": ts}
        rows_out.append(row)
        print(f"| {label} | {rows} | {name} | {path} | {row['best_us']:.0f} | {row['median_us']:.0f} "
              f"| {100 * row['fraction_of_peak']:.0f} % |")
    out = Path(args.out) if args.out else Path(__file__).parents[1] / "results" / f"network_paths_speed-{cpu_kind(cpu)}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"cpu": cpu, "threads": args.threads, "allocator": allocator, "rounds": args.rounds,
                               "calls": args.calls,
                               "fma_network_isa": fma_network.isa(), "peaks_gflops": pk, "rows": rows_out},
                              indent=1))
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
