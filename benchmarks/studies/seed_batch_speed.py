"""Exploring S seeds of one method at once: S processes side by side, one process with the seeds one
after another, or one process with the seeds' planning stacked into one model call. Is the third
worth building? This measures the bound.

    python benchmarks/studies/seed_batch_speed.py                    # S = 2 (one per core), SoftAE, fp32
    python benchmarks/studies/seed_batch_speed.py --precision bf16

The work is what dominates an uncertainty method's exploration run: one MPC action per control step
(SoftAE: the paper's iCEM, P=200, K=20, 5 iterations, one particle, the arm's (58, 12) and H=10),
each seed with its own paper-sized ensemble (5 x 4 x 256). Three ways to spend the machine's
``--threads`` cores on S seeds:

  processes   S worker processes side by side, ``threads // S`` threads each, one seed each (how the
              replication runs are run: ``--threads 1`` twice)
  sequential  one process, all threads, the S seeds' actions one after another
  stacked     one process, all threads, one planner call over ONE ensemble of S x 5 members: the
              hidden layers are exactly the S seeds' layers stacked (groups = S x 5, the same rows
              per member), the mean/sigma/reward work is the S seeds' elementwise work. It is an
              upper bound on what stacking could gain: it samples and ranks one population instead
              of S and its first layer reads one input instead of S, both of which stacking would
              still pay.

Reported as actions per second over all S seeds, the three modes interleaved for ``--repeats``
rounds (at least 5), median and best. Stacking is worth building only where it beats
``processes`` by more than the noise. Prints the CPU (vendor, AVX-512, AVX512-BF16, AMX); results:
stdout and benchmarks/results/seed_batch_speed-KIND[-bf16].json.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import statistics
import sys
import time
import warnings
from pathlib import Path

import torch
from tensordict import TensorDict

sys.path.insert(0, str(Path(__file__).parents[1]))
from planning_speed import (  # noqa: E402
    I, K, P, allocator_option, bf16_option, check_precision, cpu_description, cpu_kind, make_model, softae_env,
    use_allocator)

from torchrl_softae.modules import ICEMPlanner  # noqa: E402
from torchrl_softae.modules.planners.contract import PLANNING_PRECISIONS  # noqa: E402

D_S, D_A, H = 58, 12, 10  # the arm


def softae_planner(ensemble_size: int, seed: int, precision: str) -> ICEMPlanner:
    model = make_model(D_S, D_A, seed=seed, ensemble_size=ensemble_size)
    return ICEMPlanner(softae_env(model), planning_horizon=H, optim_steps=I, num_candidates=P, top_k=K, num_particles=1,
                       precision=precision, seed=seed)


def act(planner: ICEMPlanner, actions: int) -> float:
    """Seconds for ``actions`` MPC actions (fresh plans: the warm start does not change the cost)."""
    obs = TensorDict({"observation": torch.zeros(D_S)}, [])
    t = time.perf_counter()
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for _ in range(actions):
            planner(obs.clone())
    return time.perf_counter() - t


def worker(conn, seed: int, threads: int, precision: str, allocator: str) -> None:
    use_allocator(allocator)  # each seed's process allocates as the stacked one does
    torch.set_num_threads(threads)
    planner = softae_planner(5, seed, precision)
    act(planner, 1)  # warm-up: allocations, weight caches, inference path chosen at first use
    conn.send("ready")
    while (actions := conn.recv()) is not None:
        conn.send(act(planner, actions))


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=2, help="S, the seeds explored at once")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--actions", type=int, default=5, help="MPC actions per seed per round")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--precision", choices=PLANNING_PRECISIONS, default="fp32")
    p.add_argument("--out", default=None, help="default benchmarks/results/seed_batch_speed-KIND[-bf16].json")
    allocator_option(p)
    bf16_option(p)
    args = p.parse_args()
    check_precision(p, args.precision, args.force_bf16)
    if args.seeds < 2 or args.threads % args.seeds:
        p.error(f"--seeds {args.seeds} with --threads {args.threads}: expected at least 2 seeds that divide the threads")
    S, repeats = args.seeds, max(args.repeats, 5)
    allocator = use_allocator(args.allocator)
    cpu = cpu_description()
    suffix = "" if args.precision == "fp32" else f"-{args.precision}"
    out = (Path(args.out) if args.out
           else Path(__file__).parents[1] / "results" / f"seed_batch_speed-{cpu_kind(cpu)}{suffix}.json")
    print(f"# seed_batch_speed: torch {torch.__version__}, {args.threads} threads, {cpu['cpu']}; AVX-512 {cpu['avx512f']}, "
          f"AVX512-BF16 {cpu['avx512_bf16']}, AMX {cpu['amx_bf16']}; {S} SoftAE seeds, (58, 12), H={H}, "
          f"{args.precision}; allocator: {allocator}", flush=True)

    ctx = mp.get_context("spawn")
    pipes, procs = [], []
    for seed in range(S):
        here, there = ctx.Pipe()
        proc = ctx.Process(target=worker, args=(there, seed, args.threads // S, args.precision, args.allocator), daemon=True)
        proc.start()
        pipes.append(here)
        procs.append(proc)
    for conn in pipes:
        conn.recv()
    torch.set_num_threads(args.threads)
    singles = [softae_planner(5, seed, args.precision) for seed in range(S)]
    stacked = softae_planner(5 * S, 0, args.precision)
    for planner in (*singles, stacked):
        act(planner, 1)

    def processes() -> float:
        t = time.perf_counter()
        for conn in pipes:
            conn.send(args.actions)
        for conn in pipes:
            conn.recv()
        return time.perf_counter() - t

    modes = {"processes": processes,
             "sequential": lambda: sum(act(planner, args.actions) for planner in singles),
             "stacked": lambda: act(stacked, args.actions)}
    seconds = {m: [] for m in modes}
    for r in range(repeats):  # interleaved: each mode once per round
        for name, fn in modes.items():
            seconds[name].append(fn())
        print(f"round {r + 1}/{repeats}: " + ", ".join(f"{m} {seconds[m][-1]:.2f} s" for m in modes), flush=True)
    for conn in pipes:
        conn.send(None)
    for proc in procs:
        proc.join()

    total = S * args.actions  # actions over all seeds per round
    rate = {m: {"median": total / statistics.median(v), "best": total / min(v)} for m, v in seconds.items()}
    print(f"\n| {S} seeds, {args.precision}, {args.threads} threads | actions/s (median) | actions/s (best) "
          "| vs processes (median) |")
    print("|---|---|---|---|")
    for m in modes:
        print(f"| {m} | {rate[m]['median']:.2f} | {rate[m]['best']:.2f} "
              f"| {rate[m]['median'] / rate['processes']['median']:.2f}x |")
    result = {"cpu": cpu, "torch": torch.__version__, "threads": args.threads, "seeds": S, "precision": args.precision,
              "allocator": allocator, "actions_per_seed_per_round": args.actions, "repeats": repeats, "shape": [D_S, D_A], "horizon": H,
              "seconds": seconds, "actions_per_second": rate}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
