"""Zero-shot evaluation of E episodes as one batch (one planner call per step for all E states)
vs one episode after another, same model, same planner settings, same seeded episodes.

    python benchmarks/studies/eval_batch_speed.py                      # Pendulum-hanging and SoftFish-v0, E = 8, fp32
    python benchmarks/studies/eval_batch_speed.py --precision bf16     # the planner's hidden layers in bf16

The model is a paper-sized ensemble (5 x 4 x 256) with normalizers fitted on random transitions
(speed does not depend on training); the planner is the paper's iCEM (P=200, K=20, 5 iterations)
with mean propagation (one particle), H from the env's defaults; episodes are cut to ``--steps``
control steps (the ratio does not depend on it). The two modes are interleaved for ``--repeats``
rounds (at least 3) and reported as median and best, so one slow round on a noisy machine cannot
make the ratio. Why batching pays at all: E states make every planner call E times as many model
rows, and a 5 x 256 layer at 206 rows (one state) runs below the GEMM peak, while the per-step
elementwise work costs about the same for 1 or 8 states. What bounds it: the ensemble FLOPs of
each mode are counted as they run (every ``network_output`` call's rows, log-variance head only where it
is computed) and put against the GEMM peak of the planner's dtype measured in the same run: a
batch can at best run them at that peak, so "at most" = one-after-another's time / the batch's
FLOPs at the peak, whatever the implementation. A tighter bound is measured too: the batch's own
network calls, recorded in each round and replayed alone right after it (same rows, heads, dtype
and inference path), so "at most, network alone" = one-after-another's time / the time of those
calls with nothing else to do. Prints the CPU (vendor, AVX-512, AVX512-BF16,
AMX); results: stdout and benchmarks/results/eval_batch_speed-KIND[-bf16].json (KIND: amx,
avx512-bf16 or no-bf16).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parents[1]))
from planning_speed import (  # noqa: E402
    NetworkCallsAlone, RecordNetworkCalls, allocator_option, best_peaks, bf16_option, check_precision, cpu_description,
    cpu_kind, peaks, use_allocator)

from torchrl_softae.modules.planners.contract import PLANNING_PRECISIONS  # noqa: E402
from torchrl_softae.pipeline.builders import build_world_model  # noqa: E402
from torchrl_softae.pipeline.catalog import get_env_entry  # noqa: E402
from torchrl_softae.pipeline.config import apply_overrides, make_config  # noqa: E402
from torchrl_softae.pipeline.data import make_real_env  # noqa: E402
from torchrl_softae.pipeline.evaluate import zero_shot  # noqa: E402


def model_for(env_id: str, cfg):
    env = make_real_env(get_env_entry(env_id), 50)
    data = env.rollout(300, break_when_any_done=False)
    env.close()
    obs, act, nxt = data["observation"], data["action"], data["next", "observation"]
    model = build_world_model(cfg.model, obs.shape[-1], act.shape[-1])
    model.fit_normalizers(obs, act, nxt)
    return model.eval()


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=["Pendulum-hanging", "SoftFish-v0"])
    p.add_argument("--episodes", type=int, default=8)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--precision", choices=PLANNING_PRECISIONS, default="fp32",
                   help="the planner's hidden-layer precision (default fp32, the record's first column)")
    p.add_argument("--out", default=None, help="default benchmarks/results/eval_batch_speed-KIND[-bf16].json")
    allocator_option(p)
    bf16_option(p)
    args = p.parse_args()
    check_precision(p, args.precision, args.force_bf16)
    allocator = use_allocator(args.allocator)
    repeats = max(args.repeats, 3)
    torch.set_num_threads(args.threads)
    cpu = cpu_description()
    suffix = "" if args.precision == "fp32" else f"-{args.precision}"
    out = (Path(args.out) if args.out
           else Path(__file__).parents[1] / "results" / f"eval_batch_speed-{cpu_kind(cpu)}{suffix}.json")
    print(f"# eval_batch_speed: torch {torch.__version__}, {args.threads} threads, {cpu['cpu']}; AVX-512 {cpu['avx512f']}, "
          f"AVX512-BF16 {cpu['avx512_bf16']}, AMX {cpu['amx_bf16']}; planner precision {args.precision}; allocator: {allocator}", flush=True)
    # the GEMM peak the ratios are held against: bf16's for --precision bf16, fp32's otherwise ("auto" too)
    peak_dtype = "bf16" if args.precision == "bf16" else "fp32"
    pk = peaks(precisions=(peak_dtype,))
    results = {"cpu": cpu, "threads": args.threads, "repeats": repeats, "precision": args.precision,
               "allocator": allocator, "envs": {}}
    for env_id in args.envs:
        cfg = apply_overrides(make_config(env_id, "softae", wandb="disabled"), [f"planner.precision={args.precision}"])
        model = model_for(env_id, cfg)
        task = next(iter(get_env_entry(env_id).tasks.values()))
        task = replace(task, horizon=args.steps)
        times = {"batched": [], "sequential": []}
        flops = {"batched": [], "sequential": []}
        alone_times = []  # the batch's network calls replayed alone, right after it
        starts = {}
        for _ in range(repeats):  # interleaved: one evaluation of each mode per round
            for mode in times:
                with RecordNetworkCalls(model) as calls:
                    t = time.perf_counter()
                    res = zero_shot(cfg, model, task, episodes=args.episodes, seed=0, progress=False,
                                    batched=mode == "batched")
                    times[mode].append(time.perf_counter() - t)
                flops[mode].append(calls.flops())
                starts[mode] = res["initial_states"]
                if mode == "batched":
                    with torch.no_grad():
                        alone = NetworkCallsAlone(calls, args.precision)
                        t = time.perf_counter()
                        alone()
                        alone_times.append(time.perf_counter() - t)
            # between rounds, so a noisy moment cannot set the peak
            pk = peaks(repeats=2, so_far=pk, precisions=(peak_dtype,))
        med = {m: statistics.median(v) for m, v in times.items()}
        best = {m: min(v) for m, v in times.items()}
        row = {"task": task.name, "episodes": args.episodes, "steps": args.steps, "horizon": cfg.planner.horizon,
               "times_s": times, "batched_median_s": med["batched"], "sequential_median_s": med["sequential"],
               "speedup_median": med["sequential"] / med["batched"], "speedup_best": best["sequential"] / best["batched"],
               "network_gflop": {m: statistics.median(v) / 1e9 for m, v in flops.items()},
               "batched_network_alone_s": alone_times,
               "max_speedup_network_alone": med["sequential"] / statistics.median(alone_times),
               "same_initial_states": starts["batched"] == starts["sequential"]}
        results["envs"][env_id] = row
        print(f"{env_id} ({task.name}, {args.episodes} episodes x {args.steps} steps, H={cfg.planner.horizon}, "
              f"{args.precision}): one after another {med['sequential']:.1f} s (best {best['sequential']:.1f}), as one "
              f"batch {med['batched']:.1f} s (best {best['batched']:.1f}) -> {row['speedup_median']:.2f}x median, "
              f"{row['speedup_best']:.2f}x best; same initial states: {row['same_initial_states']}", flush=True)
    # what bounds the ratio, against the best peaks of the whole run
    peak = best_peaks(pk)[peak_dtype]
    results.update(peaks_gflops=pk, peak_gflops=peak)
    print(f"GEMM peaks (2048^3, best of the start and every round) [GFLOP/s]: "
          + ", ".join(f"{k} {v:.0f}" for k, v in pk.items()) + f"; the planner's dtype: {peak:.0f}")
    for env_id, row in results["envs"].items():
        gflop, at_peak = row["network_gflop"], row["network_gflop"]["batched"] / peak
        frac = {m: gflop[m] / (row[f"{m}_median_s"] * peak) for m in gflop}
        row.update(fraction_of_peak=frac, batched_seconds_at_peak=at_peak,
                   max_speedup_at_peak=row["sequential_median_s"] / at_peak)
        print(f"{env_id}: ensemble {gflop['sequential']:.0f} / {gflop['batched']:.0f} GFLOP (one after another / "
              f"batch), {100 * frac['sequential']:.0f} % / {100 * frac['batched']:.0f} % of the peak; the batch's "
              f"FLOPs at the peak take {at_peak:.1f} s, so a batch is at most {row['max_speedup_at_peak']:.2f}x "
              f"faster than one after another ({row['speedup_median']:.2f}x measured); its network calls alone "
              f"take {statistics.median(row['batched_network_alone_s']):.1f} s: at most "
              f"{row['max_speedup_network_alone']:.2f}x with nothing but them to do")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
