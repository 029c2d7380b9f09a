"""SoftAE-MBPO against MBPO, MBPO-TS and Random (paper supplement, Fig. S2 / Table S8), resumable.

    python benchmarks/mbpo_compare.py --runs random:0 mbpo:0 mbpo-ts:0 softae:0 --threads 1
    python benchmarks/mbpo_compare.py --table              # the table from every finished result
    python benchmarks/mbpo_compare.py --plot               # return vs real transitions, per task

Every method gets the same real transitions (``--budgets`` exploration episodes of the env's
length) and the same number of SAC updates per task (``policy.updates_per_step`` x transitions):

* ``random``, ``softae``: explore task-agnostically (random actions; SoftAE's iCEM on ||sigma||
  with hallucinated control), then ``softae policy`` trains a SAC policy per task on the model
  (mean propagation): Random-MBPO and SoftAE-MBPO.
* ``mbpo``, ``mbpo-ts``: collect with their own SAC policy for task (i), the model retrained and
  the policy trained on it after every episode (mean / trajectory-sampling rollouts). Their task
  (i) policy is that one; for task (ii) ``softae policy`` trains a new one on their model (same
  propagation).

Real returns over ``--eval-episodes`` seeded episodes per task (the episodes zero-shot
evaluation uses). One compact JSON per (method, seed, budget) in
``benchmarks/results/mbpo/ENV/`` as soon as it is finished; rerunning skips finished ones and
resumes killed runs (exploration and policy training both checkpoint).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from torchrl_softae.pipeline.arguments import PRESETS
from torchrl_softae.pipeline.cli import plain_output
from torchrl_softae.pipeline.plots import method_color

RESULTS = Path(__file__).parent / "results" / "mbpo"
SETUPS = {  # env -> (task (i), task (ii), preset, overrides)
    "Pendulum-hanging": ("swingup", "spin", "quick", []),
    # the paper's MBPO setting (symlog model, Table S6-S8); SAC at the quick preset's sizes: Table S8's 3 x 1024 networks
    # at 20 updates per transition cost about 12 h per task policy here (benchmarks/studies/mbpo_cost.py)
    "SoftArm-v1": ("reach-close", "reach-far", "mbpo",
                   ["planner.precision=auto", *[o for o in PRESETS["quick"] if o.startswith("policy.")]]),
}
LABELS = {"random": "Random-MBPO", "mbpo": "MBPO", "mbpo-ts": "MBPO-TS", "softae": "SoftAE-MBPO"}
PAPER = "paper (Fig. S2): SoftAE-MBPO matches MBPO/MBPO-TS on (i), clearly beats them on (ii); Random lags"


def run_one(env: str, method: str, seed: int, budgets: list[int], eval_episodes: int, root: Path,
            overrides: list[str], tag: str = "") -> None:
    from torchrl_softae.pipeline.config import make_config
    from torchrl_softae.pipeline.explore import explore
    from torchrl_softae.pipeline.methods import get_method
    from torchrl_softae.pipeline.policy import train_policy

    task_i, task_ii, preset, env_overrides = SETUPS[env]
    m = get_method(method)
    for budget in budgets:
        out = RESULTS / (env + tag) / f"{method}-s{seed}-ep{budget}.json"
        if out.exists():
            continue
        cfg = make_config(env, method, [*PRESETS[preset], *env_overrides, *overrides], episodes=budget, seed=seed, wandb="disabled",
                          task=task_i if m.needs_task else None)
        run_dir = root / (env + tag) / f"{method}-s{seed}"
        t0 = time.time()
        history = explore(cfg, run_dir, progress=False, echo=None)
        t_explore = time.time() - t0
        tasks = {}
        for task in (task_i, task_ii):
            propagation = m.policy_propagation
            t0 = time.time()
            res = train_policy(run_dir, task, propagation=propagation, episodes=eval_episodes, seed=seed,
                               progress=False, echo=None)
            tasks[task] = {"returns": res["returns"], "mean_return": res["mean_return"], "metrics": res["metrics"],
                           "updates": res["updates_done"], "from_run_policy": res["from_run_policy"],
                           "seconds_this_call": time.time() - t0}
        result = {"env": env, "method": method, "label": LABELS.get(method, method), "seed": seed, "episodes": budget,
                  "transitions": history[-1]["transitions"], "explore_seconds_this_call": t_explore,
                  "policy_updates_per_task": cfg.policy.updates_per_step * history[-1]["transitions"],
                  "heldout_nmse": history[-1]["heldout_nmse"], "tasks": tasks, "config": cfg.to_dict(),
                  "history": [{k: v for k, v in row.items() if isinstance(v, (int, float))} for row in history]}
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=1, default=float))
        print(f"{env + tag}/{out.name}: " + ", ".join(f"{t} {v['mean_return']:.1f}" for t, v in tasks.items()), flush=True)


def _rows(env: str, tag: str = "") -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((RESULTS / (env + tag)).glob("*.json"))]


def _fmt(values, fmt="{:.1f}") -> str:
    v = np.asarray(values, dtype=float)
    return (fmt.format(v.mean()) + (" +- " + fmt.format(v.std(ddof=1)) if len(v) > 1 else "")) if len(v) else "-"


def table(env: str, tag: str = "") -> str:
    rows = _rows(env, tag)
    if not rows:
        return f"{env + tag}: no finished result yet"
    task_i, task_ii = SETUPS[env][:2]
    order = [m for m in LABELS if any(r["method"] == m for r in rows)]
    lines = []
    for budget in sorted({r["episodes"] for r in rows}):
        group = [r for r in rows if r["episodes"] == budget]
        lines += [f"\n{env + tag}, {budget} episodes = {group[0]['transitions']} real transitions per run, "
                  f"{group[0]['policy_updates_per_task']} SAC updates per task; real return, mean +- std over seeds\n",
                  f"| method | seeds | (i) {task_i} | (ii) {task_ii} | held-out nMSE | compute per run [min] |",
                  "|---|---|---|---|---|---|"]
        for m in order:
            rs = [r for r in group if r["method"] == m]
            if not rs:
                continue
            # exploration of all episodes (collect + model + MBPO's own policy) + this budget's task policies
            wall = [(sum(h.get("collect_seconds", 0) + h.get("train_seconds", 0) + h.get("policy_seconds", 0)
                         for h in r["history"]) + sum(t["seconds_this_call"] for t in r["tasks"].values())) / 60
                    for r in rs]
            lines.append(f"| {LABELS[m]} | {len(rs)} | {_fmt([r['tasks'][task_i]['mean_return'] for r in rs])} | "
                         f"{_fmt([r['tasks'][task_ii]['mean_return'] for r in rs])} | "
                         f"{_fmt([r['heldout_nmse'] for r in rs], '{:.3g}')} | {_fmt(wall)} |")
    lines.append(f"\n{PAPER}")
    return "\n".join(lines)


def plot(env: str, tag: str = "") -> Path | None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = _rows(env, tag)
    if not rows:
        return None
    task_i, task_ii = SETUPS[env][:2]
    methods = [m for m in LABELS if any(r["method"] == m for r in rows)]
    all_budgets = sorted({r["transitions"] for r in rows})
    # methods side by side around each budget (dodged), so that equal budgets do not hide each other
    gap = min(np.diff(all_budgets)) if len(all_budgets) > 1 else all_budgets[0]
    width = 0.5 * gap / max(len(methods), 1) if len(all_budgets) > 1 else 0.15 * gap / max(len(methods), 1)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharex=True)
    for j, (task, role) in enumerate(((task_i, "(i), MBPO's training task"), (task_ii, "(ii), unseen by MBPO"))):
        ax = axes[j]
        for c, m in enumerate(methods):
            budgets = sorted({r["transitions"] for r in rows if r["method"] == m})
            vals = [[r["tasks"][task]["mean_return"] for r in rows if r["method"] == m and r["transitions"] == b]
                    for b in budgets]
            mean, std = np.array([np.mean(v) for v in vals]), np.array([np.std(v, ddof=1) if len(v) > 1 else 0.0 for v in vals])
            n = sorted({len(v) for v in vals})
            x = np.array(budgets, dtype=float) + (c - (len(methods) - 1) / 2) * width
            ax.errorbar(x, mean, yerr=std, marker="o", capsize=3, color=method_color(m),
                        label=f"{LABELS[m]} ({'/'.join(map(str, n))} seeds)")
            for xi, v in zip(x, vals):  # every seed
                ax.plot([xi] * len(v), v, ".", color=method_color(m), alpha=0.45, ms=5)
        ax.set_xticks(all_budgets)
        if len(all_budgets) == 1:
            ax.set_xlim(all_budgets[0] - 0.25 * gap, all_budgets[0] + 0.25 * gap)
        ax.set_title(f"{task} {role}", fontsize=11)
        ax.set_xlabel("real transitions")
        ax.set_ylabel("real return (mean +- std; dots: seeds)")
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8)  # below, off the curves
    per = rows[0]["policy_updates_per_task"] // rows[0]["transitions"]
    fig.suptitle(f"{env}: SAC on the learned model, {per} updates per real transition per task policy; real-env returns",
                 fontsize=10)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    path = RESULTS / (env + tag) / "return_vs_transitions.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main():
    plain_output()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="Pendulum-hanging", choices=sorted(SETUPS))
    p.add_argument("--runs", nargs="*", default=[], metavar="METHOD:SEED", help="run these, one after another")
    p.add_argument("--budgets", type=int, nargs="+", default=[2, 5])
    p.add_argument("--eval-episodes", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--root", default=str(Path(__file__).parent / "results" / "runs" / "mbpo"))
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--tag", default="", help="a variant's suffix for the results folder (e.g. +symlog with "
                                             "--set model.symlog=true)")
    p.add_argument("--table", action="store_true", help="print the table of finished results and exit")
    p.add_argument("--plot", action="store_true", help="draw return vs real transitions and exit")
    args = p.parse_args()
    if args.table or args.plot:
        print(table(args.env, args.tag))
        if args.plot:
            print(plot(args.env, args.tag))
        return
    torch.set_num_threads(args.threads)
    for item in args.runs:
        method, seed = item.split(":")
        run_one(args.env, method, int(seed), args.budgets, args.eval_episodes, Path(args.root), args.overrides,
                args.tag)
    print(table(args.env, args.tag))


if __name__ == "__main__":
    main()
