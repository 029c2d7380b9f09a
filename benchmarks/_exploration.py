"""Driver of the last exploration script (``exploration_mujoco.py``, the target fish, until its sweep
replaces it): methods x seeds at an equal transition budget,
then held-out normalized MSE, coverage and zero-shot task returns. Resumable: rerunning skips
finished runs and evaluations."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import torch

from torchrl_softae.pipeline.cli import PRESETS, plain_output
from torchrl_softae.pipeline.config import make_config
from torchrl_softae.pipeline.evaluate import REFERENCE_POLICIES, evaluate_run, reference_returns
from torchrl_softae.pipeline.explore import explore
from torchrl_softae.pipeline.plots import plot_comparison

RESULTS = Path(__file__).parent / "results"


def run(args, tasks: list[str], overrides: list[str], note: str = "", references: bool = False) -> str:
    """Explore + evaluate every (method, seed); print and save a markdown table; return it.

    ``references``: add rows with the task returns of model-free references (random actions and
    no control) on the same evaluation episodes, to tell solving a task from not trying."""
    plain_output()
    torch.set_num_threads(args.threads)
    root = Path(args.root or RESULTS / "runs" / f"exploration_{args.env}")
    rows: dict[str, list] = {}
    for method in args.methods:
        for seed in args.seeds:
            cfg = make_config(args.env, method, PRESETS["quick"] + overrides + args.overrides,
                              episodes=args.episodes, seed=seed, wandb="disabled")
            run_dir = root / f"{method}-s{seed}"
            history = explore(cfg, run_dir, progress=True)
            row = {"seed": seed, "transitions": history[-1]["transitions"], "coverage": history[-1]["coverage"],
                   **{k: v for k, v in history[-1].items() if k.startswith("heldout_nmse")}}
            for task in tasks:
                f = run_dir / "eval" / f"{task}.json"
                res = json.loads(f.read_text()) if f.exists() else None
                stale = res is None or res.get("episodes") != args.eval_episodes or \
                    res.get("episodes_explored") != history[-1]["episode"] + 1
                if stale:
                    res = evaluate_run(run_dir, tasks=[task], episodes=args.eval_episodes, seed=777)["tasks"][task]
                row[f"{task}/return"] = float(np.mean(res["returns"]))
            rows.setdefault(method, []).append(row)
            print(method, seed, row, flush=True)

    def ms(vals, fmt):
        return f"{np.mean(vals):{fmt}} ± {np.std(vals):{fmt}}"

    budget = rows[args.methods[0]][0]["transitions"]
    # the metric and its groups (the legacy metric stays in the JSON, not in the table)
    nmse_cols = sorted(k for k in rows[args.methods[0]][0] if k == "heldout_nmse" or k.startswith("heldout_nmse/"))
    cols = nmse_cols + ["coverage"] + [f"{t}/return" for t in tasks]
    names = {"heldout_nmse": "held-out normalized MSE", "coverage": "coverage"}
    names.update({k: f"normalized MSE ({k.split('/', 1)[1]})" for k in nmse_cols if "/" in k})
    names.update({f"{t}/return": f"{t} return" for t in tasks})
    lines = [f"{args.env}: {budget} transitions per run ({args.episodes} episodes), seeds {args.seeds}, "
             f"`quick` preset{note}, zero-shot tasks over {args.eval_episodes} episodes (mean propagation); "
             f"mean ± std over seeds" + ("; reference rows over the evaluation episodes" if references else ""), "",
             "| method | " + " | ".join(names[c] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for m in args.methods:
        cells = [ms([r[c] for r in rows[m]], ".4g" if c.startswith("heldout_nmse") else ".3g") for c in cols]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    if references:
        cache = root / "references.json"
        known = json.loads(cache.read_text()) if cache.exists() else {}
        for policy, label in REFERENCE_POLICIES.items():
            for task in tasks:
                key = f"{task}/{policy}/{args.eval_episodes}"
                if key not in known:
                    known[key] = reference_returns(args.env, task, policy, args.eval_episodes, seed=777)
            cache.write_text(json.dumps(known, indent=1))
            by_col = {f"{t}/return": known[f"{t}/{policy}/{args.eval_episodes}"] for t in tasks}
            cells = [ms(by_col[c], ".3g") if c in by_col else "-" for c in cols]
            lines.append(f"| *{label}* | " + " | ".join(cells) + " |")
        rows["references"] = known
    table = "\n".join(lines)
    print("\n" + table)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"exploration_{args.env}.json").write_text(json.dumps(rows, indent=1))
    (RESULTS / f"exploration_{args.env}.md").write_text(table + "\n")
    plots = RESULTS / "plots"
    plots.mkdir(exist_ok=True)
    for f in plot_comparison(root):
        shutil.copy(f, plots / f"{args.env}_{f.name}")
        print(plots / f"{args.env}_{f.name}")
    return table
