"""Why the arm's held-out error grows with data: the incremental training schedule, measured.

    python benchmarks/studies/arm_training_schedule.py benchmarks/results/runs/arm_v1/softae-s0 --threads 1
    python benchmarks/studies/arm_training_schedule.py --table     # by group and method, every result

During exploration the ensemble is retrained after every episode from its previous weights
(Table S6: lr 5e-5, 50 epochs capped at 5000 gradient steps), and its input/output normalizers
are refit to the grown data first, so the weights meet shifted inputs and targets every episode.
This script takes a finished run's data and model and compares, on the held-out metric of the
replication (reference-set std):

* ``run``: the run's own model (trained incrementally, as explored);
* ``fresh-paper``: a new ensemble trained once on all of the data with the same schedule;
* ``fresh-*``: the same with other learning rates / epochs / step caps / weight decay
  (``--schedules``), applied to every method alike (issue #54's held-out study).

If a fresh model at the same schedule is much better than the run's, the incremental schedule,
not the data the method collected, is what limits the replication's model accuracy. Every model is
scored overall and by group of state dimensions, beside s' = s and predict-the-mean.
Results: ``benchmarks/results/arm_training_schedule/RUNNAME.json``.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

RESULTS = Path(__file__).parents[1] / "results" / "arm_training_schedule"


def main():
    from torchrl_softae.objectives import EnsembleLoss, EnsembleTrainer
    from torchrl_softae.pipeline.builders import build_world_model
    from torchrl_softae.pipeline.catalog import get_env_entry
    from torchrl_softae.pipeline.data import ModelAccuracy
    from torchrl_softae.pipeline.evaluate import load_run
    from torchrl_softae.pipeline.policy import stored_transitions
    from torchrl_softae.pipeline.runs import RunDir

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="*", help="finished run dirs")
    p.add_argument("--schedules", nargs="*", default=["5e-5:50:5000", "1e-3:50:5000", "1e-3:50:5000:1e-4",
                                                      "1e-3:1000:20000"],
                   metavar="LR:EPOCHS:MAX_STEPS[:WEIGHT_DECAY]",
                   help="default: the paper's, its epochs at lr 1e-3 (without and with weight decay), a long one")
    p.add_argument("--table", action="store_true", help="print the table of every result by group and method, and exit")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    if args.table:
        print(table())
        return
    if not args.runs:
        p.error("name the finished run dirs to study (or --table)")
    torch.set_num_threads(args.threads)
    for run_dir in args.runs:
        cfg, model, state = load_run(run_dir)
        run = RunDir(run_dir)
        data = stored_transitions(run, state)
        accuracy = ModelAccuracy(get_env_entry(cfg.env), run, cfg.heldout_size)
        out = {"run": str(run_dir), "env": cfg.env, "method": cfg.method, "seed": cfg.seed,
               "episodes": state["episode"] + 1, "transitions": len(data), **accuracy.baselines,
               "models": {"run": {"schedule": "incremental (as explored)", **accuracy(model)}}}
        print(f"{run_dir}: {len(data)} transitions; run's model {out['models']['run']['heldout_nmse']:.4g} "
              f"(s' = s {accuracy.baselines['heldout_nmse_identity']:.4g})", flush=True)
        for spec in args.schedules:
            fields = spec.split(":")
            lr, epochs, steps = float(fields[0]), int(fields[1]), int(fields[2])
            wd = float(fields[3]) if len(fields) > 3 else 0.0
            torch.manual_seed(args.seed)
            fresh = build_world_model(cfg.model, model.observation_dim, model.action_dim)
            trainer = EnsembleTrainer(EnsembleLoss(fresh), lr=lr, batch_size=cfg.train.batch_size, epochs=epochs,
                                      max_grad_steps=steps, val_fraction=cfg.train.val_fraction, weight_decay=wd)
            t0 = time.time()
            report = trainer.fit(data, generator=torch.Generator().manual_seed(args.seed))
            name = f"fresh lr {lr:g}, {report.grad_steps} steps" + (f", weight decay {wd:g}" if wd else "")
            out["models"][name] = {"lr": lr, "grad_steps": report.grad_steps, "weight_decay": wd,
                                   "seconds": time.time() - t0, "val_mse": report.final_val_mse,
                                   **accuracy(fresh.eval())}
            print(f"  {name}: {out['models'][name]['heldout_nmse']:.4g} ({time.time() - t0:.0f} s)", flush=True)
        RESULTS.mkdir(parents=True, exist_ok=True)
        (RESULTS / f"{Path(run_dir).name}-ep{out['episodes']}.json").write_text(json.dumps(out, indent=1, default=float))


def table() -> str:
    """Every result: per episodes, model (run's or fresh schedule) and method, the held-out nMSE overall and by group
    (mean +- sample std over seeds, n), with the s' = s and predict-the-mean rows."""
    import numpy as np

    results = [json.loads(p.read_text()) for p in sorted(RESULTS.glob("*.json"))]
    lines = []
    for episodes in sorted({r["episodes"] for r in results}):
        rs = [r for r in results if r["episodes"] == episodes]
        groups = [k.split("/", 1)[1] for k in rs[0]["models"]["run"] if k.startswith("heldout_nmse/")]
        keys = ["heldout_nmse", *(f"heldout_nmse/{g}" for g in groups)]
        lines += [f"\n{rs[0]['env']}, {episodes} episodes: held-out nMSE (mean ± sample std over seeds, n)\n",
                  "| model | method | n | overall | " + " | ".join(g.replace("_", " ") for g in groups) + " |",
                  "|---|---|---|---|" + "---|" * len(groups)]
        for name, suffix in (("s' = s", "_identity"), ("predict the mean", "_mean")):
            lines.append(f"| {name} | - | - | " + " | ".join(
                f"{rs[0][k.replace('heldout_nmse', 'heldout_nmse' + suffix)]:.3g}" for k in keys) + " |")
        models = list(dict.fromkeys(m for r in rs for m in r["models"]))
        for model in models:
            for method in dict.fromkeys(r["method"] for r in rs):
                group = [r["models"][model] for r in rs if r["method"] == method and model in r["models"]]
                if not group:
                    continue

                def pm(values):
                    v = np.asarray(values, dtype=float)
                    return f"{v.mean():.3g}" + (f" ± {v.std(ddof=1):.2g}" if len(v) > 1 else "")

                lines.append(f"| {model} | {method} | {len(group)} | "
                             + " | ".join(pm([g[k] for g in group]) if all(k in g for g in group) else "-"
                                          for k in keys) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
