"""What a small op costs right after a network call, against the same op in a loop.

    python benchmarks/studies/cold_ops.py [--rounds 5] [--calls 300]

A one-particle plan's model step is one network call and a handful of small ops on (206, d_s)
tensors before the next call. Timed in a loop, each small op costs a few microseconds; the plan
measured far more between its network calls. This times each small op (median of ``--calls``)
right after one of several "predecessors" (nothing: the op in a loop; the ensemble's whole network
at the arm's 206 rows, bf16 and fp32, as the planner calls it; a 16 MiB elementwise pass; a 0.4 ms
sleep), the predecessors interleaved in ``--rounds`` rounds, and prints the median over rounds. A
4-element ``add`` touches almost no data: what it pays after a network call is the cost of its
code and the interpreter's, evicted by the call. This is why ``EnsembleWorldModel.
deterministic_rollout`` runs a step as two prepared kernel calls (benchmarks/README.md, "What the planner
computes less, and how it runs it"). Writes ``benchmarks/results/cold_ops-KIND.json``.
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
from planning_speed import cpu_description, cpu_kind, make_model  # noqa: E402

from torchrl_softae.allocator import keep_freed_memory  # noqa: E402
from torchrl_softae.modules.engine import moments_kernel  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--calls", type=int, default=300, help="timed calls of each op after each predecessor per round")
    p.add_argument("--out", default=None, help="default benchmarks/results/cold_ops-KIND.json")
    args = p.parse_args()
    if args.rounds < 1 or args.calls < 1:
        p.error(f"--rounds {args.rounds} and --calls {args.calls}: expected positive counts")
    keep_freed_memory()
    cpu = cpu_description()
    d_s, d_a, rows = 58, 12, 206  # the arm, one-particle planning's rows
    model = make_model(d_s, d_a)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(rows, d_s + d_a, generator=g)
    big = torch.randn(4 << 20, generator=g)  # 16 MiB
    tiny = torch.ones(4)
    mu, sigma, eta = (torch.randn(rows, d_s, generator=g) for _ in range(3))

    def network(dtype):
        def call():
            model.network_output(x, with_logvar=False, dtype=dtype)
        return call

    predecessors = {"nothing (the op in a loop)": lambda: None,
                    "whole network, bf16, 206 rows": network(torch.bfloat16),
                    "whole network, fp32, 206 rows": network(None),
                    "16 MiB elementwise pass": lambda: big.mul_(1.0),
                    "0.4 ms sleep": lambda: time.sleep(4e-4)}
    with torch.no_grad():
        raw = model.network_output(x, with_logvar=False)
    out_norm = model.output_normalizer
    ops = {"add, 4 elements": lambda: tiny.add(1.0),
           "addcmul, 206 x 58": lambda: torch.addcmul(mu, sigma, eta),
           "linalg.vector_norm, 206 x 58": lambda: torch.linalg.vector_norm(sigma, dim=-1, keepdim=True),
           "zeros_like, 206 x 1": lambda: torch.zeros_like(mu[:, :1])}
    if moments_kernel.available():
        ops["moments pass (compiled), 5 x 206 x 58"] = lambda: moments_kernel.ensemble_moments(
            raw, mu, out_norm.loc, out_norm.scale, d_s)
    print(f"# cold_ops: torch {torch.__version__}, {torch.get_num_threads()} threads, {cpu['cpu']}; AVX-512 "
          f"{cpu['avx512f']}, AVX512-BF16 {cpu['avx512_bf16']}, AMX {cpu['amx_bf16']}", flush=True)
    times = {(op, pre): [] for op in ops for pre in predecessors}
    with torch.no_grad():
        for _ in range(args.rounds):
            for pre_name, pre in predecessors.items():
                for op_name, op in ops.items():
                    for _ in range(10):  # warm: the predecessor's own first calls
                        pre()
                        op()
                    t = []
                    for _ in range(args.calls):
                        pre()
                        s = time.perf_counter()
                        op()
                        t.append(time.perf_counter() - s)
                    times[(op_name, pre_name)].append(statistics.median(t))
    rows_out = [{"op": op, "after": pre, "median_us": 1e6 * statistics.median(times[(op, pre)]),
                 "rounds_us": [1e6 * v for v in times[(op, pre)]]} for op in ops for pre in predecessors]
    names = list(predecessors)
    print("\n| op, us (median of rounds) | " + " | ".join(f"after {n}" for n in names) + " |")
    print("|---|" + "---|" * len(names))
    for op in ops:
        print(f"| {op} | " + " | ".join(f"{1e6 * statistics.median(times[(op, n)]):.1f}" for n in names) + " |")
    out = Path(args.out) if args.out else Path(__file__).parents[1] / "results" / f"cold_ops-{cpu_kind(cpu)}.json"
    out.write_text(json.dumps({"cpu": cpu, "threads": torch.get_num_threads(), "rounds": args.rounds,
                               "calls": args.calls, "rows": rows_out}, indent=1))
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
