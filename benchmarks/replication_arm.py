"""The soft-arm replication (issue: SoftAE vs the baselines at a budget that learns), resumable.

    python benchmarks/replication_arm.py --runs softae:0 random:0 random:1 --threads 1
    python benchmarks/replication_arm.py --table          # the table from every finished result
    python benchmarks/replication_arm.py --plot           # nMSE vs episode, returns vs budget
    python benchmarks/replication_arm.py --coverage 50    # tip heatmaps by method at a budget

Each ``METHOD:SEED`` explores ``SoftArm-v1`` (or ``--env SoftArm136-v1``, Fig. 3C) at the paper's model, training and iCEM settings
(Tables S6, S7; the ``paper`` preset), ``planner.precision=auto`` (bf16 where the CPU has native
bf16; it keeps the candidate ranking, ``test_bf16_ranking_matches_fp32``). After each budget of
``--budgets`` exploration episodes it evaluates zero-shot (mean propagation, H = 10): (i)
reach-close and (ii) reach-far one episode each (the arm starts at rest: deterministic), and
reach-any over ``--any-episodes`` targets drawn from the held-out distribution; and it records the
held-out normalized MSE (reference-set std), with the s' = s and predict-the-mean baselines.

Every finished (run, budget) is written at once as compact JSON to
``benchmarks/results/arm_v1/METHOD-sSEED-epBUDGET.json`` (``arm136_v1/`` for the 136D arm) (history up to the budget + evaluation),
so results survive the run dirs; rerunning skips finished budgets and resumes a killed run.
H-UCRL explores optimistically on task (i), as in the paper.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from planning_speed import cpu_description  # noqa: E402

from torchrl_softae.modules.engine import moments_kernel, paths, silu_kernel  # noqa: E402
from torchrl_softae.pipeline.data import COVERAGE_BINS  # noqa: E402
from torchrl_softae.pipeline.plots import method_color  # noqa: E402
from torchrl_softae.pipeline.replication import code_version  # noqa: E402

#: env -> results folder name (and run dirs' folder under results/runs/)
SETUPS = {"SoftArm-v1": "arm_v1", "SoftArm136-v1": "arm136_v1"}


def results_dir(env: str) -> Path:
    return Path(__file__).parent / "results" / SETUPS[env]
TASKS = ["reach-close", "reach-far", "reach-any"]
#: bins per axis of the tip histogram in each result; twice the coverage metric's, so pooling
#: 2 x 2 cells gives back the metric's grid (checked against the recorded coverage)
HIST_BINS = 2 * COVERAGE_BINS
PAPER = {"random": 0.2397, "hucrl": 0.7232, "softae": 0.0526}


def tip_histogram(env: str, run_dir: Path, heldout_size: int) -> dict:
    """Transitions per tip cell (x, z) of every transition in ``run_dir``, on the env's fixed
    coverage grid at ``HIST_BINS`` per axis: the heatmaps are drawn from the results, not the run dirs."""
    from torchrl_softae.pipeline.catalog import get_env_entry
    from torchrl_softae.pipeline.data import coverage_counts, heldout_set, projection_bounds
    from torchrl_softae.pipeline.runs import RunDir

    entry, run = get_env_entry(env), RunDir(run_dir)
    state = run.load()
    rb = run.load_replay_buffer(state)
    bounds = projection_bounds(entry, heldout_set(entry, run, heldout_size))
    counts = coverage_counts(entry, rb.storage[: len(rb)], bounds, HIST_BINS)
    return {"bins": HIST_BINS, "bounds": bounds.tolist(), "labels": list(entry.projection_labels),
            "transitions": len(rb), "counts": counts.tolist()}


def pooled_coverage(hist: dict) -> float:
    """The coverage metric (share of visited cells of the ``COVERAGE_BINS`` grid) from a tip histogram."""
    c = np.asarray(hist["counts"])
    k = hist["bins"] // COVERAGE_BINS
    pooled = c.reshape(COVERAGE_BINS, k, COVERAGE_BINS, k).sum((1, 3))
    return float((pooled > 0).sum()) / COVERAGE_BINS**2


def check_histogram(result: dict, hist: dict) -> None:
    """A histogram belongs to a result only if it holds its transitions and gives its coverage."""
    want = result["history"][-1]
    if hist["transitions"] != want["transitions"] or abs(pooled_coverage(hist) - want["coverage"]) > 1e-9:
        raise ValueError(f"{result['method']}-s{result['seed']}-ep{result['episodes']}: the run dir holds "
                         f"{hist['transitions']} transitions with coverage {pooled_coverage(hist):.4f}, the result "
                         f"{want['transitions']} with {want['coverage']:.4f}: not the same data")


def run_one(env: str, method: str, seed: int, budgets: list[int], any_episodes: int, root: Path,
            overrides: list[str]) -> None:
    from torchrl_softae.pipeline.config import make_config
    from torchrl_softae.pipeline.evaluate import evaluate_run
    from torchrl_softae.pipeline.explore import explore

    for budget in budgets:
        out = results_dir(env) / f"{method}-s{seed}-ep{budget}.json"
        if out.exists():
            continue
        cfg = make_config(env, method, ["planner.precision=auto", *overrides], episodes=budget, seed=seed,
                          wandb="disabled", task="reach-close" if method == "hucrl" else None)
        run_dir = root / f"{method}-s{seed}"
        t0 = time.time()
        # One flushed line per episode: stdout is usually a log file beside a second run.
        history = explore(cfg, run_dir, progress=False,
                          echo=lambda line: print(f"{env} {method}-s{seed}: {line}", flush=True))
        t_explore = time.time() - t0
        t0 = time.time()
        fixed = evaluate_run(run_dir, tasks=["reach-close", "reach-far"], episodes=1, seed=0, progress=False)
        anyres = evaluate_run(run_dir, tasks=["reach-any"], episodes=any_episodes, seed=0, progress=False)
        tasks = {**fixed["tasks"], **anyres["tasks"]}
        result = {
            "env": env, "method": method, "seed": seed, "episodes": budget, "transitions": history[-1]["transitions"],
            "history": history, "explore_seconds_this_call": t_explore, "eval_seconds": time.time() - t0,
            "accuracy": {k: v for k, v in fixed.items() if k.startswith("heldout_nmse")},
            "tasks": {name: {"returns": r["returns"], "mean_return": r["mean_return"],
                             "final_error_mm": [m["final_error_mm"] for m in r["metrics"]],
                             "min_error_mm": [m["min_error_mm"] for m in r["metrics"]]} for name, r in tasks.items()},
            "config": cfg.to_dict(),
            # With precision=auto and measured kernel choices a seed's actions depend on the
            # machine's arithmetic (bf16 or fp32, which GEMM, chosen anew where the cache is new,
            # which instruction set the compiled kernels run on): the same seed with other choices
            # is another run. The choices are this process's (a resumed run's earlier episodes may
            # have planned with others).
            "machine": {**cpu_description(), "torch": torch.__version__, "threads": torch.get_num_threads(),
                        "kernel_choices": paths.choices(), "silu_kernel_isa": silu_kernel.isa(),
                        "moments_kernel_isa": moments_kernel.isa()},
            "code": code_version(),
            "tip_histogram": tip_histogram(env, run_dir, cfg.heldout_size),
        }
        check_histogram(result, result["tip_histogram"])
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=1, default=float))
        print(f"{out.name}: nmse {result['accuracy']['heldout_nmse']:.4g}, "
              + ", ".join(f"{k} {v['mean_return']:.1f} ({np.mean(v['final_error_mm']):.0f} mm)"
                          for k, v in result["tasks"].items()), flush=True)


def table(env: str) -> str:
    rows = [json.loads(p.read_text()) for p in sorted(results_dir(env).glob("*.json"))]
    if not rows:
        return "no finished result yet"
    from torchrl_softae.pipeline.methods import METHOD_NAMES

    lines = []
    for budget in sorted({r["episodes"] for r in rows}):
        group = [r for r in rows if r["episodes"] == budget]
        lines += [f"\n{env}, {budget} exploration episodes = {group[0]['transitions']} transitions per run "
                  "(paper preset, iCEM H=10, mean +- sample std over seeds; our held-out set is not the "
                  "paper's, so the last column compares nMSE ratios to Random's, never the values)\n",
                  "| method | seeds | held-out nMSE | s'=s | predict mean | coverage | (i) return | (i) final error [mm] | "
                  "(ii) return | (ii) final error [mm] | reach-any return | reach-any final error [mm] | nMSE / Random's (paper's) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        random_nmse = [r["accuracy"]["heldout_nmse"] for r in group if r["method"] == "random"]
        for m in [m for m in METHOD_NAMES if any(r["method"] == m for r in group)]:
            rs = [r for r in group if r["method"] == m]

            def f(values, fmt="{:.3g}"):
                v = np.asarray(values, dtype=float)
                return (fmt.format(v.mean()) + (" +- " + fmt.format(v.std(ddof=1)) if len(v) > 1 else "")) if len(v) else "-"

            cells = [m, str(len(rs)), f([r["accuracy"]["heldout_nmse"] for r in rs]),
                     f([r["accuracy"]["heldout_nmse_identity"] for r in rs]),
                     f([r["accuracy"]["heldout_nmse_mean"] for r in rs]),
                     f([r["history"][-1]["coverage"] for r in rs], "{:.2f}")]
            for t in TASKS:
                cells += [f([r["tasks"][t]["mean_return"] for r in rs], "{:.1f}"),
                          f([np.mean(r["tasks"][t]["final_error_mm"]) for r in rs], "{:.0f}")]
            ratio = (np.mean([r["accuracy"]["heldout_nmse"] for r in rs]) / np.mean(random_nmse)) if random_nmse else None
            paper = f" ({PAPER[m] / PAPER['random']:.2f})" if env == "SoftArm-v1" and m in PAPER else ""  # the 58D arm's
            cells.append("-" if ratio is None else f"{ratio:.2f}{paper}")
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(env: str) -> Path | None:
    """Held-out nMSE vs exploration episode (every seed, and the mean where 2+ seeds have the
    episode) and zero-shot returns vs budget (mean +- std over seeds), per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_softae.pipeline.methods import METHOD_NAMES

    rows = [json.loads(p.read_text()) for p in sorted(results_dir(env).glob("*.json"))]
    if not rows:
        return None
    methods = [m for m in METHOD_NAMES if any(r["method"] == m for r in rows)]
    fig, axes = plt.subplots(1, 1 + len(TASKS), figsize=(4.2 * (1 + len(TASKS)), 3.8))
    for c, m in enumerate(methods):
        rs = [r for r in rows if r["method"] == m]
        longest = {}  # the longest history of each seed
        for r in rs:
            if r["episodes"] > longest.get(r["seed"], {"episodes": 0})["episodes"]:
                longest[r["seed"]] = r
        curves = [[h["heldout_nmse"] for h in r["history"]] for r in longest.values()]
        for y in curves:
            axes[0].plot(range(1, len(y) + 1), y, color=method_color(m), alpha=0.3, lw=1)
        n = max(len(y) for y in curves)
        mean = [np.mean([y[k] for y in curves if len(y) > k]) for k in range(n)]
        seeds = [sum(len(y) > k for y in curves) for k in range(n)]
        shown = [k for k in range(n) if seeds[k] >= 2]
        axes[0].plot([k + 1 for k in shown], [mean[k] for k in shown], color=method_color(m), lw=2.5,
                     label=f"{m} ({len(curves)} seeds; thick: mean of 2+)")
        budgets = sorted({r["episodes"] for r in rs})
        for j, t in enumerate(TASKS):
            vals = [[r["tasks"][t]["mean_return"] for r in rs if r["episodes"] == b] for b in budgets]
            x = np.array(budgets, dtype=float) + 0.35 * (c - (len(methods) - 1) / 2)  # dodged: no method hides another
            axes[j + 1].errorbar(x, [np.mean(v) for v in vals], yerr=[np.std(v, ddof=1) if len(v) > 1 else 0 for v in vals], marker="o",
                                 capsize=3, color=method_color(m), label=f"{m} ({'/'.join(str(len(v)) for v in vals)} seeds)")
            for xi, v in zip(x, vals):  # every seed
                axes[j + 1].plot([xi] * len(v), v, ".", color=method_color(m), alpha=0.45, ms=4)
    identity = rows[0]["accuracy"]["heldout_nmse_identity"]
    axes[0].axhline(identity, color="k", ls="--", lw=1, label=f"s' = s ({identity:.3f})")
    axes[0].set_yscale("log")
    axes[0].set_title(f"{env}: held-out normalized MSE")
    axes[0].set_xlabel("exploration episode (200 transitions each)")
    axes[0].set_ylabel("normalized MSE (reference-set std)")
    axes[0].legend(fontsize=7)
    for j, t in enumerate(TASKS):
        ax = axes[j + 1]
        ax.set_title(f"{env}: zero-shot {t}")
        ax.set_xlabel("exploration episodes")
        ax.set_ylabel("return (sum of g(d), max 200)")
        ax.set_xticks(sorted({r["episodes"] for r in rows}))
        ax.set_ylim(bottom=0)
        ax.legend(fontsize=7)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    path = results_dir(env).parent / "plots" / f"{env}_replication_curves.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def add_histograms(env: str, root: Path) -> list[str]:
    """Adds the tip histogram to every result that lacks one and whose run dir below ``root``
    (``METHOD-sSEED``) holds exactly its transitions and coverage (checked); returns what it did."""
    done = []
    for path in sorted(results_dir(env).glob("*.json")):
        result = json.loads(path.read_text())
        run_dir = root / f"{result['method']}-s{result['seed']}"
        if "tip_histogram" in result or not (run_dir / "checkpoint.pt").exists():
            continue
        hist = tip_histogram(env, run_dir, result["config"]["heldout_size"])
        if hist["transitions"] != result["transitions"]:
            continue  # the run dir is at another budget
        check_histogram(result, hist)
        result["tip_histogram"] = {**hist, "source": f"added from the run dir {run_dir.name} (--add-histograms)"}
        path.write_text(json.dumps(result, indent=1, default=float))
        done.append(f"{path.name}: tip histogram from {run_dir}")
    return done


def plot_coverage(env: str, budget: int) -> Path | None:
    """Tip heatmaps by method at ``budget`` episodes (transitions per cell, averaged over the
    method's seeds so methods with different seed counts compare) on the env's fixed grid with one
    colour scale, the targets of (i) and (ii) marked, from the results that carry a tip histogram."""
    from torchrl_softae.pipeline.catalog import get_env_entry
    from torchrl_softae.pipeline.methods import METHOD_NAMES
    from torchrl_softae.pipeline.plots import coverage_heatmaps

    rows = [json.loads(p.read_text()) for p in sorted(results_dir(env).glob(f"*-ep{budget}.json"))]
    rows = [r for r in rows if "tip_histogram" in r]
    if not rows:
        return None
    counts, first = {}, rows[0]["tip_histogram"]
    for m in [m for m in METHOD_NAMES if any(r["method"] == m for r in rows)]:
        rs = sorted((r for r in rows if r["method"] == m), key=lambda r: r["seed"])
        if any(r["tip_histogram"]["bounds"] != first["bounds"] for r in rs):
            raise ValueError(f"{env}: tip histograms on different grids: held-out sets differ between results")
        label = (f"{m} (seed{'s' * (len(rs) > 1)} {','.join(str(r['seed']) for r in rs)}; cov. "
                 f"{np.mean([r['history'][-1]['coverage'] for r in rs]):.2f})")
        counts[label] = np.mean([np.asarray(r["tip_histogram"]["counts"]) for r in rs], 0)
    (x0, z0), (x1, z1) = first["bounds"]
    edges = [np.linspace(x0, x1, first["bins"] + 1), np.linspace(z0, z1, first["bins"] + 1)]
    tasks = get_env_entry(env).tasks
    targets = {f"{tag} {name}": (tasks[name].params["target"][0], tasks[name].params["target"][2])
               for tag, name in (("(i)", "reach-close"), ("(ii)", "reach-far")) if name in tasks}
    path = results_dir(env).parent / "plots" / f"{env}_tip_coverage_{budget}ep.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    return coverage_heatmaps(counts, edges, first["labels"],
                             f"{env}: tip positions visited in {budget} exploration episodes "
                             f"({rows[0]['transitions']} transitions per seed)\ngrid: the held-out targets' range; "
                             "edge cells also hold what lies beyond", path,
                             unit="transitions per cell (mean over seeds)", markers=targets)


def main():
    from torchrl_softae.pipeline.cli import plain_output

    plain_output()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="SoftArm-v1", choices=sorted(SETUPS))
    p.add_argument("--runs", nargs="*", default=[], metavar="METHOD:SEED", help="run these, one after another")
    p.add_argument("--budgets", type=int, nargs="+", default=[10, 25, 50])
    p.add_argument("--any-episodes", type=int, default=3)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--root", default=None, help="run dirs (default benchmarks/results/runs/arm_v1 or arm136_v1)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--table", action="store_true", help="print the table of finished results and exit")
    p.add_argument("--plot", action="store_true", help="draw nMSE vs episode and returns vs budget, and exit")
    p.add_argument("--coverage", type=int, metavar="BUDGET", help="draw the tip heatmaps by method at BUDGET, and exit")
    p.add_argument("--add-histograms", action="store_true",
                   help="add tip histograms to results that lack one, from run dirs below --root, and exit")
    args = p.parse_args()
    from torchrl_softae.pipeline.methods import METHOD_NAMES

    runs = []
    for item in args.runs:
        method, _, seed = item.partition(":")
        if method not in METHOD_NAMES or not seed.isdigit():
            p.error(f"--runs {item!r}: expected METHOD:SEED with METHOD one of {', '.join(METHOD_NAMES)} "
                    "and SEED a non-negative integer")
        runs.append((method, int(seed)))
    root = Path(args.root) if args.root else Path(__file__).parent / "results" / "runs" / SETUPS[args.env]
    if args.add_histograms:
        print("\n".join(add_histograms(args.env, root)) or "no result gained a histogram")
        return
    if args.coverage is not None:
        print(plot_coverage(args.env, args.coverage) or f"no result at {args.coverage} episodes has a tip histogram")
        return
    if args.table or args.plot:
        print(table(args.env))
        if args.plot:
            print(plot(args.env))
        return
    torch.set_num_threads(args.threads)
    for method, seed in runs:
        run_one(args.env, method, seed, args.budgets, args.any_episodes, root, args.overrides)
    print(table(args.env))


if __name__ == "__main__":
    main()
