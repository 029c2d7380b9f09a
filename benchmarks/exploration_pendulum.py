"""Random vs Mean-AE vs PETS-AE vs SoftAE at an equal transition budget on a pendulum.

    python benchmarks/exploration_pendulum.py                       # Pendulum-v1, 3 seeds (~40 min on 2 cores)
    python benchmarks/exploration_pendulum.py --env Pendulum-hanging
    python benchmarks/exploration_pendulum.py --episodes 2 --seeds 0  # smoke run

Every method explores task-agnostically for EPISODES x 200 transitions with the ``quick`` preset
(the method is the paper's, sizes are shrunk for a CPU), then the same model and planner solve
the swing-up task zero-shot (mean propagation). Reported per method (mean +- std over seeds):
held-out normalized next-state MSE (2000 uniform state-action transitions of the true pendulum),
state coverage, and the zero-shot swing-up return. Runs are resumable: rerunning skips what is
done. Results: benchmarks/results/exploration_<env>.json and .md, plots in the runs folder.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from torchrl_softae.cli import PRESETS
from torchrl_softae.config import make_config
from torchrl_softae.evaluate import evaluate_run
from torchrl_softae.explore import explore
from torchrl_softae.plotting import plot_comparison

METHODS = ["random", "mean-ae", "pets-ae", "softae"]


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="Pendulum-v1")
    p.add_argument("--episodes", type=int, default=8)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--eval-episodes", type=int, default=3)
    p.add_argument("--methods", nargs="+", default=METHODS)
    p.add_argument("--root", default=None, help="runs folder (default benchmarks/results/runs/exploration_ENV)")
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    here = Path(__file__).parent / "results"
    root = Path(args.root or here / "runs" / f"exploration_{args.env}")
    rows = {}
    for method in args.methods:
        for seed in args.seeds:
            cfg = make_config(args.env, method, PRESETS["quick"] + ["planner.horizon=20", "heldout_size=2000"],
                              episodes=args.episodes, seed=seed, wandb="disabled")
            run_dir = root / f"{method}-s{seed}"
            history = explore(cfg, run_dir, progress=True)
            eval_file = run_dir / "eval" / "swingup.json"
            if eval_file.exists() and json.loads(eval_file.read_text())["episodes"] == args.eval_episodes:
                swing = json.loads(eval_file.read_text())
            else:
                swing = evaluate_run(run_dir, tasks=["swingup"], episodes=args.eval_episodes, seed=777)["tasks"]["swingup"]
            rows.setdefault(method, []).append({
                "seed": seed, "transitions": history[-1]["transitions"], "heldout_nmse": history[-1]["heldout_nmse"],
                "coverage": history[-1]["coverage"], "swingup_return": float(np.mean(swing["returns"])),
                "upright_fraction": float(np.mean([m["upright_fraction_last_half"] for m in swing["metrics"]])),
            })
            print(method, seed, rows[method][-1], flush=True)

    def ms(vals, fmt):
        return f"{np.mean(vals):{fmt}} ± {np.std(vals):{fmt}}"

    budget = rows[args.methods[0]][0]["transitions"]
    lines = [
        f"{args.env}: {budget} transitions per run ({args.episodes} episodes x 200), seeds {args.seeds}, "
        f"`quick` preset, zero-shot swing-up over {args.eval_episodes} episodes (mean propagation)",
        "",
        "| method | held-out normalized MSE | coverage | swing-up return | upright fraction (last 100 steps) |",
        "|---|---|---|---|---|",
    ]
    for m in args.methods:
        r = rows[m]
        lines.append(f"| {m} | {ms([x['heldout_nmse'] for x in r], '.4f')} | {ms([x['coverage'] for x in r], '.3f')} | "
                     f"{ms([x['swingup_return'] for x in r], '.0f')} | {ms([x['upright_fraction'] for x in r], '.2f')} |")
    table = "\n".join(lines)
    print("\n" + table)
    here.mkdir(parents=True, exist_ok=True)
    (here / f"exploration_{args.env}.json").write_text(json.dumps(rows, indent=1))
    (here / f"exploration_{args.env}.md").write_text(table + "\n")
    for f in plot_comparison(root):
        print(f)


if __name__ == "__main__":
    main()
