"""Plans with glibc's default malloc against :func:`torchrl_softae.keep_freed_memory`, process
against process.

    python benchmarks/studies/allocator_speed.py                  # 5 rounds, the arm's shape (58, 12), H=10
    python benchmarks/studies/allocator_speed.py --rounds 3 --threads 1

An allocator setting is process-wide, so the two cannot be interleaved inside one process: each
round runs one child process per setting, in alternating order, and each child times its
contenders the same way (two warm-up calls, then ``--plans`` of each, interleaved). Plans and the
large call run in separate children: the large call's allocations change glibc's heap, and with
it whether the plans' allocations fault. The
contenders are those of ``planning_speed.py`` at the paper's iCEM settings: TorchRL's
``CEMPlanner`` (under ``torch.no_grad()``), our iCEM with 10 particles and with one (SoftAE), fp32
and bf16 (bf16 only where the CPU has it natively, as ``planning_speed.py`` decides), plus one
network call at the rows of 8 such plans as one batch (``eval_batch_speed.py`` and
``seed_batch_speed.py`` make calls that large). Every child reports its median ms, the minor
page faults per plan and its peak resident memory; the table gives, per contender, the median over
rounds of each setting and the ratio default / kept (median and best of the rounds' ratios).
Results: stdout and benchmarks/results/allocator_speed-KIND.json (KIND: amx, avx512-bf16 or
no-bf16).
"""
from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parents[1]))
from planning_speed import ALLOCATORS, cpu_description, cpu_kind  # noqa: E402

#: rows of one network call standing for 8 plans as one batch (8 x 2060: 10 particles)
BATCH_ROWS = 8 * 2060


#: what one child process times: planners, or the large network call (apart: its 84 MiB
#: allocations change glibc's heap, and with it whether the plans' allocations fault)
GROUPS = ("plans", "batch")


def child(group: str, setting: str, plans: int, threads: int, d_s: int, d_a: int, H: int) -> dict:
    """Times the contenders of ``group`` in this process under ``setting``; returns its measurements."""
    import torch
    from tensordict import TensorDict
    from torchrl.modules import CEMPlanner

    from planning_speed import (
        ICEM_ROWS, I, K, N, P, contender_precision, icem_contender, icem_settings, make_model, pets_env, softae_env,
        timed_precisions, use_allocator)

    from torchrl_softae.modules.engine.precision import resolve_planning_dtype

    allocator = use_allocator(setting)
    precisions = timed_precisions()  # bf16 only where it is native
    torch.set_num_threads(threads)
    model = make_model(d_s, d_a)
    obs = TensorDict({"observation": torch.randn(d_s)}, [])
    if group == "plans":
        sample_env, opt_env = pets_env(model), softae_env(model)
        jobs = {"cem-torchrl": CEMPlanner(sample_env, H, I, P * N, K)}  # as planning_speed.py runs it
        jobs.update({key: icem_contender(key, sample_env, opt_env, icem_settings(H))[0] for key in ICEM_ROWS
                     if contender_precision(key) in precisions})
    else:
        batch = torch.randn(BATCH_ROWS, d_s + d_a)

        def batch_call(dtype):
            def fn(_obs):
                model.network_output(batch, dtype=dtype)
            return fn

        jobs = {f"network-8-plans-{name}": batch_call(resolve_planning_dtype(name)) for name in precisions}
    faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt  # noqa: E731
    times = {k: [] for k in jobs}
    fault_counts = {k: [] for k in jobs}
    with torch.no_grad():
        for fn in jobs.values():
            fn(obs.clone())
            fn(obs.clone())
        for _ in range(plans):
            for key, fn in jobs.items():
                f0, t0 = faults(), time.perf_counter()
                fn(obs.clone())
                times[key].append(time.perf_counter() - t0)
                fault_counts[key].append(faults() - f0)
    return {"setting": setting, "allocator": allocator,
            "ms": {k: 1e3 * statistics.median(v) for k, v in times.items()},
            "faults_per_call": {k: statistics.median(v) for k, v in fault_counts.items()},
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def run_child(group: str, setting: str, args) -> dict:
    cmd = [sys.executable, __file__, "--child", group, setting, "--plans", str(args.plans), "--threads", str(args.threads),
           "--shape", *map(str, args.shape)]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=Path(__file__).parents[1])
    if out.returncode != 0:
        raise RuntimeError(f"child ({group}, {setting}) failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--plans", type=int, default=3, help="timed plans of each contender per child (after 2 warm-up)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--shape", type=int, nargs=3, default=[58, 12, 10], metavar=("D_S", "D_A", "H"))
    p.add_argument("--child", nargs=2, metavar=("GROUP", "ALLOCATOR"), help=argparse.SUPPRESS)
    p.add_argument("--out", default=None, help="default benchmarks/results/allocator_speed-KIND.json")
    args = p.parse_args()
    for name, value, low in (("--rounds", args.rounds, 3), ("--plans", args.plans, 1), ("--threads", args.threads, 1)):
        if value < low:
            p.error(f"{name}={value}: expected at least {low}")
    if args.child:
        print(json.dumps(child(*args.child, args.plans, args.threads, *args.shape)))
        return 0
    cpu = cpu_description()
    out_path = Path(args.out) if args.out else Path(__file__).parents[1] / "results" / f"allocator_speed-{cpu_kind(cpu)}.json"
    print(f"# allocator_speed: {cpu['cpu']}; AVX-512 {cpu['avx512f']}, AVX512-BF16 {cpu['avx512_bf16']}, "
          f"AMX {cpu['amx_bf16']}; {args.threads} threads, shape {tuple(args.shape)}, {args.rounds} rounds of one "
          f"child per setting (alternating order), {args.plans} plans per contender per child", flush=True)
    rounds = []
    for r in range(args.rounds):
        order = ALLOCATORS if r % 2 == 0 else ALLOCATORS[::-1]
        res = {s: {"ms": {}, "faults_per_call": {}, "peak_rss_mib": {}} for s in ALLOCATORS}
        for group in GROUPS:
            for s in order:
                one = run_child(group, s, args)
                res[s]["allocator"] = one["allocator"]
                res[s]["ms"].update(one["ms"])
                res[s]["faults_per_call"].update(one["faults_per_call"])
                res[s]["peak_rss_mib"][group] = one["peak_rss_mib"]
        rounds.append(res)
        print(f"round {r + 1}/{args.rounds} (default / kept): " + ", ".join(
            f"{k} {res['default']['ms'][k]:.0f} / {res['kept']['ms'][k]:.0f} ms" for k in res["default"]["ms"]),
            flush=True)
    if rounds[0]["kept"]["allocator"] != "kept freed memory":
        print(f"both settings ran glibc's default here: {rounds[0]['kept']['allocator']}")
    rows = []
    print("\n| contender | default malloc, ms | kept freed memory, ms | default / kept (median, best) "
          "| page faults per call, default / kept |")
    print("|---|---|---|---|---|")
    for key in rounds[0]["default"]["ms"]:
        ms = {s: statistics.median(r[s]["ms"][key] for r in rounds) for s in ALLOCATORS}
        ratios = [r["default"]["ms"][key] / r["kept"]["ms"][key] for r in rounds]
        flt = {s: statistics.median(r[s]["faults_per_call"][key] for r in rounds) for s in ALLOCATORS}
        rows.append({"contender": key, "ms": ms, "ratio_median": statistics.median(ratios),
                     "ratio_best": max(ratios), "faults_per_call": flt})
        print(f"| {key} | {ms['default']:.0f} | {ms['kept']:.0f} | {statistics.median(ratios):.2f}x, "
              f"{max(ratios):.2f}x | {flt['default']:.0f} / {flt['kept']:.0f} |")
    rss = {g: {s: statistics.median(r[s]["peak_rss_mib"][g] for r in rounds) for s in ALLOCATORS} for g in GROUPS}
    print("peak resident memory of a child (median), default / kept: "
          + ", ".join(f"{g} {rss[g]['default']:.0f} / {rss[g]['kept']:.0f} MiB" for g in GROUPS))
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps({"cpu": cpu, "threads": args.threads, "shape": args.shape, "plans": args.plans,
                                    "rows": rows, "peak_rss_mib": rss, "rounds": rounds}, indent=1))
    print(f"wrote {out_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
